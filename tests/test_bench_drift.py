"""`focustrack bench drift` in a tiny version: every scenario, its JSON and its figure."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from focustrack.bench.focus import REAL_DIR
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


#: Small enough that a bench run by mistake (a value not refused) ends in seconds.
TINY = ["--size", "6", "--maps", "1", "--ekf-trials", "5", "--check-textures", "1"]


@pytest.mark.parametrize(
    ("flag", "value", "allowed"),
    [
        ("--settle-tau-s", "0", "above 0"),  # these were tracebacks
        ("--settle-tau-s", "-5", "above 0"),
        ("--walk-um-per-sqrt-min", "-1", ">= 0"),
        ("--lateral-tiles", "0", "in [1, 10000]"),
        ("--ekf-trials", "0", "[1, 10000]"),
        ("--laser-noise-um", "inf", ">= 0"),
        ("--seed", "-1", "[0, 4294967295]"),
        ("--maps", "0", "[1, 10000]"),  # these four shared one message naming no flag
        ("--size", "1", "[2, 1000]"),
        ("--noise-um", "nan", "above 0"),
        ("--dof-um", "0", "above 0"),
        ("--frame-check-ratio", "1", "[0, 1)"),
        ("--check-textures", "0", "in [1, 10000]"),
    ],
)
def test_a_bad_value_is_refused_before_any_work_naming_its_flag_and_range(
    flag: str, value: str, allowed: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "drift", *TINY, flag, value])
    assert stopped.value.code == 2
    captured = capsys.readouterr()
    assert f"argument {flag}: " in captured.err and allowed in captured.err
    assert captured.out == ""  # no scenario began


def test_a_real_dir_that_is_not_there_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    """It was taken, and the real-data rows left out without a word."""
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "drift", *TINY, "--real-dir", "/nonexistent"])
    assert stopped.value.code == 2
    assert "argument --real-dir: /nonexistent is not a folder" in capsys.readouterr().err


def test_the_command_line_refuses_a_bad_value_in_one_line(tmp_path: Path) -> None:
    """The installed command, as a user runs it: exit status 2 and a usage line, no
    traceback."""
    command = Path(sys.executable).with_name("focustrack")
    done = subprocess.run(
        [str(command), "bench", "drift", *TINY, "--settle-tau-s", "0"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert done.returncode == 2
    assert "focustrack bench drift: error: argument --settle-tau-s: must be" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.skipif(
    not (REAL_DIR / "wsi_focus_curves").is_dir(), reason="no real whole-slide focus curves here"
)
def test_few_ekf_trials_keep_the_real_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Below 20 trials a real field got none (trials // 20 = 0) and its rows went unsaid."""
    out = tmp_path / "drift.json"
    assert main(["bench", "drift", *TINY, "--json", str(out)]) == 0
    capsys.readouterr()
    sources = json.loads(out.read_text())["ekf"]
    assert any(source.startswith("real wsi") for source in sources), sources
