"""`focustrack bench phase --sweep` on a tiny setting: its table, JSON keys and figure."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import phase
from focustrack.bench.focus import REAL_DIR
from focustrack.bench.phase import OBJECTS, run
from focustrack_phase import simulate


def test_the_bench_writes_its_table_json_and_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # the filter's settings searched on a small grid: this checks the bench, not the search
    monkeypatch.setattr(phase, "FILTER_Q0", (0.1, 1.0))
    monkeypatch.setattr(phase, "FILTER_P0_RATIO", (0.0,))
    monkeypatch.setattr(phase, "FILTER_PRIOR_LENGTH_UM", (0.0, 2.0))
    monkeypatch.setattr(phase, "SIMULATOR_SEEDS", (1,))  # one slide: the bench, not the seeds
    out = tmp_path / "phase.json"
    args = argparse.Namespace(
        json=out, sweep=True, seed=1, size_px=16, repeats=1, speed_size_px=32, real_dir=tmp_path
    )  # no real data there: that section is skipped, and said so
    assert run(args) == 0
    result = json.loads(out.read_text())
    assert set(result) == {
        "data_set_1", "objects", "known_spectra", "sweep", "coherence", "simulator", "speed",
        "anchoring_speed", "real_yeast", "figure", "coherence_figure", "simulator_figure",
        "yeast_figure", "paper",
    }  # fmt: skip
    methods = [row["method"] for row in result["data_set_1"]]
    assert methods[0].startswith("sparse ACEKF ours") and len(methods) == 7
    assert methods[1] == "sparse ACEKF ours + background anchoring"
    assert methods[-2:] == ["flat field (reference)", "oracle Wiener (reference)"]
    row = result["data_set_1"][0]
    assert set(row) == {
        "method", "gamma", "planes", "phase_rmse_rad", "intensity_rmse", "time_s", "cpu_s"
    }  # fmt: skip
    assert row["planes"] == 100 and row["time_s"] > 0 and row["phase_rmse_rad"] > 0
    assert row["cpu_s"] > 0 and result["data_set_1"][-1]["cpu_s"] is None
    assert {row["gamma"] for row in result["sweep"]} == {0.998, 1.0, 10.0, 100.0, 1000.0}
    assert result["paper"]["sparse ACEKF (paper)"]["phase_rmse_rad"] == 0.0143
    known = result["known_spectra"]
    assert [(row["peak_phase_rad"], row["smooth_um"]) for row in known][1:] == list(OBJECTS)
    for row in known:
        assert 0 < row["oracle_rad"] < row["wiener_known_spectra_rad"]
        assert row["ours_known_spectra_rad"] > 0 and row["paper_update_known_spectra_rad"] > 0
    objects = result["objects"]
    assert [(row["peak_phase_rad"], row["smooth_um"]) for row in objects] == list(OBJECTS)
    for row in objects:
        assert 0 < row["oracle_rad"] < row["flat_rad"] and row["ours_rad"] > 0
        assert row["ours_anchored_rad"] > 0
    assert (tmp_path / result["figure"]).stat().st_size > 1000
    assert (tmp_path / result["coherence_figure"]).stat().st_size > 1000
    models = [row["model"] for row in result["coherence"]]
    assert models == [
        "coherent model (paper)", "coherent model (paper) + anchoring",
        "coherence envelope (ours)", "coherence envelope (ours) + anchoring",
    ]  # fmt: skip
    for row in result["coherence"]:
        # 16 px of 1 um: below 0.05 cycles/um there is only the mean, which is removed, so
        # the band's error is round-off (1e-18, or exactly 0: asserting > 0 was flaky)
        assert 0 <= row["low_frequency_rmse_rad"] < 1e-12 < row["phase_rmse_rad"]
    assert (tmp_path / result["simulator_figure"]).stat().st_size > 1000
    simulator = {(row["specimen"], row["model"]): row for row in result["simulator"]}
    assert len(simulator) == 6 and all(0.8 < r["correlation"] <= 1 for r in simulator.values())
    for specimen in ("phase-cells", "phase-blood"):
        # The full-size tiles: measured on seed 1, RMSE 0.312 -> 0.180 (cells), 0.126 ->
        # 0.113 (red cells); glass at -0.04 and -0.40 rad -> within 0.01 of zero.
        own = simulator[(specimen, "coherence envelope (ours)")]
        anchored = simulator[(specimen, "envelope + anchoring (ours)")]
        assert anchored["phase_rmse_rad"] < 0.95 * own["phase_rmse_rad"]
        assert anchored["low_frequency_rmse_rad"] < own["low_frequency_rmse_rad"]
        assert abs(anchored["glass_phase_rad"]) < 0.03
    anchoring = result["anchoring_speed"]
    assert anchoring["cpu_s"] > 0 and 0 < anchoring["peak_memory_images"] < 10
    speed = {row["update"]: row for row in result["speed"]}
    assert set(speed) == {"phase_frame", "paper"}
    assert all(0 < row["peak_memory_images"] < 40 and row["time_s"] > 0 for row in speed.values())
    assert all(row["cpu_s"] > 0 for row in speed.values())
    assert all(row["fft_cpu_s"] > 0 for row in speed.values())
    assert result["real_yeast"] is None and result["yeast_figure"] is None
    printed = capsys.readouterr().out
    assert "sparse ACEKF (paper)" in printed and "the real yeast z-stack: skipped" in printed


@pytest.mark.skipif(not REAL_DIR.is_dir(), reason=f"{REAL_DIR} is missing")
def test_the_phase_of_real_yeast_agrees_with_itself(tmp_path: Path) -> None:
    row, images = phase.score_real_yeast(REAL_DIR)
    # Measured: 0.998 between the even and the odd planes, 0.689 between the two sides of
    # focus; the phase spans about +-0.5 rad; no glass to anchor to.
    assert row["planes"] == 34 and row["even_odd_correlation"] > 0.95
    assert row["above_below_correlation"] > 0.5
    assert 0.2 < row["phase_p99_rad"] - row["phase_p1_rad"] < 3.0
    assert 0.0 <= row["background_share"] <= 1.0
    assert all(image.shape == (63, 60) for image in images.values())
    phase.write_images(tmp_path / "yeast.png", images)
    assert (tmp_path / "yeast.png").stat().st_size > 1000


def test_the_filter_knowing_the_object_s_spectra_comes_within_a_tenth_of_the_wiener_estimate() -> (
    None
):
    data = simulate.data_set_1(2, 10.0, 40, 48)
    realised, expected = phase.wiener_known_spectra(data)
    # Measured 0.089 against 0.086 rad; the oracle (amplitude and each bin's power known,
    # expected error) 0.048, the expected error of this Wiener estimate 0.057.
    assert phase.filter_known_spectra(data, "phase_frame") < 1.1 * realised
    assert phase.oracle_phase_rmse(data) < expected < realised
    flat = float(np.std(np.angle(data.field)))
    assert realised < 0.7 * flat
