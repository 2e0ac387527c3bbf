"""`focustrack bench drift` in a tiny version: every scenario, its JSON and its figure."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from focustrack.cli import main


def test_every_scenario_is_scored_and_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "drift.json"
    args = ["--maps", "1", "--size", "8", "--lateral-tiles", "3", "--ekf-trials", "20"]
    args += ["--check-textures", "1"]
    args += ["--json", str(out)]
    assert main(["bench", "drift", *args]) == 0
    table = capsys.readouterr().out
    for row in ("thermal: kf-2d-lean", "+time +revisits", "laser: kf-2d-laser", "second pass"):
        assert row in table
    report = json.loads(out.read_text())
    scenarios = report["scenarios"]
    assert set(scenarios) == {"thermal", "laser", "second pass"}
    for scores in scenarios.values():
        for score in scores.values():
            assert 0.0 <= score["in_focus_fraction"] <= 1.0
            assert score["frames_per_tile"] > 0 and score["time_over_limit"] >= 1.0
            assert score["revisits"] >= 0
    # the laser images most tiles once; the second pass knows the map and moves little
    assert scenarios["laser"]["kf-2d-laser"]["frames_per_tile"] < 2.0
    second = scenarios["second pass"]["kf-rescan"]
    # the slide moved 5 um (46 px) on the stage; the stage sent by the offset measured
    # puts the tiles back within half a pixel of the first pass's, by the simulator's truth
    assert second["lateral_uncorrected_px"] == pytest.approx(5.0 / 0.1083, rel=0.01)
    assert second["lateral_error_px"] <= 0.5
    # with the first-frame check: a row per stated risk, scored like the others
    checked = [label for label in scenarios["second pass"] if label.endswith("+check")]
    assert len(checked) == 2 and all(label in table for label in checked)
    for scores in report["ekf"].values():  # the EKF and the linear fit on the same samples
        assert set(scores) == {"linear fit", "ekf"}
        assert all(s["frames_per_tile"] >= 3 and s["mae_um"] >= 0 for s in scores.values())
    assert out.with_suffix(".png").stat().st_size > 0


def test_bad_sizes_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "drift", "--size", "1"]) == 2
    assert "bad sizes" in capsys.readouterr().err
    assert main(["bench", "drift", "--frame-check-ratio", "1"]) == 2
    assert "first-frame check" in capsys.readouterr().err
