"""`focustrack bench slide`, small: a virtual slide scanned through the real services by a
Kalman strategy and autofocus on every tile, a slide of unstained cells in valley mode;
and its scoring of tiles on dust, on folds and on empty glass."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from focustrack.cli import main
from focustrack.slide_scores import SlideContents, bare_glass, tile_scores
from focustrack_core.v1 import instrument_pb2
from focustrack_instrument_sim.simulator_options import SimulatorOptions


def test_tiles_are_scored_against_what_lies_in_them() -> None:
    nan = np.nan
    contents = SlideContents(
        focus_um=np.array([[0.0, 0.0, 0.0, 0.0]]),
        empty=np.array([[False, False, False, True]]),
        dust_z_um=np.array([[30.0, 30.0, nan, 30.0]]),
        fold_z_um=np.array([[nan, nan, 3.0, nan]]),
    )
    kept_um = np.array([[0.2, 29.0, 3.1, 28.0]])  # in focus, on dust, on the fold, empty
    frames = np.array([[5, 9, 5, 1]])
    risk = np.array([[0.01, 0.5, nan, 0.2]])  # the fold's tile: none stated
    scores = tile_scores(contents, kept_um, {(0, 0): [0.2, 5.0]}, frames, 0.9, risk)
    assert scores["tissue_in_focus"] == 2 and scores["tissue_tiles"] == 3
    assert scores["on_dust"] == 2 and scores["dust_tiles"] == 3
    assert (scores["empty_tiles"], scores["empty_frames"]) == (1, 1)
    # the section's 0.2 and 29 um, the fold's 0.1: the empty tile's 28 um counts nowhere
    assert scores["tissue_imaged"] == 3
    assert scores["tissue_error_um"] == pytest.approx(0.2 + 29.0 + 0.1)
    # the risk the estimator stated for the tissue's images, the empty tile's left out
    assert scores["tissue_risk_stated"] == 2
    assert scores["tissue_risk_sum"] == pytest.approx(0.51)


def test_a_slide_of_separate_fields_takes_its_bare_glass_from_the_caller() -> None:
    truth = instrument_pb2.SlideTruth(slide="slide-0", rows=1, cols=2, best_focus_um=[1.0, 2.0])
    with pytest.raises(ValueError, match="no virtual slide"):
        SlideContents.of(truth)
    contents = SlideContents.of(truth, np.array([[False, True]]))
    np.testing.assert_array_equal(contents.focus_um, [[1.0, 2.0]])
    np.testing.assert_array_equal(contents.empty, [[False, True]])
    assert np.isnan(contents.dust_z_um).all() and np.isnan(contents.fold_z_um).all()


def test_bare_glass_is_where_the_simulator_shows_no_specimen() -> None:
    for specimen in ("phase-cells", "stained-smear"):  # sparse cells; a smear's empty fields
        options = SimulatorOptions(seed=2, rows=4, cols=4, width=128, height=128, specimen=specimen)
        glass = bare_glass(options, "slide-0")
        assert glass.shape == (4, 4) and 0 < glass.sum() < 16


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_small_slide_bench_scans_through_the_services(tmp_path: Path) -> None:
    out = tmp_path / "slide.json"
    command = [
        sys.executable, "-m", "focustrack", "bench", "slide", "--seeds", "4", "--rows", "3",
        "--cols", "4", "--size", "128", "--strategies", "kf-2d-lean", "af-every-tile",
        "--out", str(tmp_path / "work"), "--json", str(out),
    ]  # fmt: skip
    bench = subprocess.run(command, capture_output=True, text=True, timeout=560)
    assert bench.returncode == 0, bench.stdout + bench.stderr
    scores = json.loads(out.read_text())["scores"]
    lean, every = scores["kf-2d-lean"], scores["af-every-tile"]
    assert every["frames_per_tile"] > 4 * lean["frames_per_tile"] > 0
    assert every["time_over_limit"] > lean["time_over_limit"] > 1.0
    # the lean rule states each image's risk, and expects most tissue in focus
    assert 0.5 < lean["tissue_stated_in_focus_fraction"] <= 1.0
    for score in (lean, every):
        assert 0.0 <= score["tissue_in_focus_fraction"] <= 1.0
        assert score["tiles_focused_on_dust"] >= 0
        assert score["seam_error_px"] < 1.0  # one specimen, placed by the stage
    assert out.with_suffix(".png").stat().st_size > 0
    assert "tissue in focus" in bench.stdout


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_with_look_first_an_empty_tile_costs_one_frame_and_tissue_its_stack(
    tmp_path: Path,
) -> None:
    """Through the real services, with look_first (the bench's default): every tile found
    empty cost one frame, the scan's first among them (its height unknown: a look at its
    prediction), the rest of a look's stack is read with the look's frame as one curve, and
    every tissue tile is in focus."""
    command = [
        sys.executable, "-m", "focustrack", "bench", "slide", "--seeds", "3", "--rows", "6",
        "--cols", "6", "--size", "256", "--strategies", "kf-2d-lean",
        "--out", str(tmp_path / "work"), "--json", str(tmp_path / "slide.json"),
    ]  # fmt: skip
    bench = subprocess.run(command, capture_output=True, text=True, timeout=560)
    assert bench.returncode == 0, bench.stdout + bench.stderr
    frames: dict[tuple[int, int], list[int]] = {}
    found_empty, joined = set(), 0
    log = tmp_path / "work" / "seed-3" / "kf-2d-lean" / "scan_log.jsonl"
    for entry in map(json.loads, log.read_text().splitlines()):
        tile = (entry.get("row"), entry.get("col"))
        if entry["event"] == "acquired":
            frames.setdefault(tile, []).append(entry["n_frames"])
        if entry["event"] == "measured" and "empty" in entry["flags"]:
            found_empty.add(tile)
        if entry["event"] == "measured" and entry["curve_z_um"] is not None:
            # a curve of one frame more than its acquisition: the look's frame joined
            joined += len(entry["curve_z_um"]) == frames[tile][-1] + 1
    assert (0, 0) in found_empty and len(found_empty) >= 4
    assert all(frames[tile] == [1] for tile in found_empty)
    assert joined >= 10
    score = json.loads((tmp_path / "slide.json").read_text())["scores"]["kf-2d-lean"]
    assert score["tissue_in_focus_fraction"] == 1.0 and score["tiles_focused_on_dust"] == 0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_slide_of_unstained_cells_is_scanned_in_valley_mode_and_scored_on_its_cells(
    tmp_path: Path,
) -> None:
    """Sparse cells in culture: the focus service looks for the contrast minimum by
    default, every tile with a cell in view is in focus, and the bare glass is scored
    apart; with --phase, a phase stack of every tile with cells and none of the glass
    (each glass tile one frame: the look's, which sees nothing in view)."""
    out = tmp_path / "cells.json"
    command = [
        sys.executable, "-m", "focustrack", "bench", "slide", "--specimen", "phase-cells",
        "--seeds", "1", "--rows", "4", "--cols", "4", "--size", "128",
        "--strategies", "kf-2d-lean", "--phase", "--out", str(tmp_path / "work"),
        "--json", str(out),
    ]  # fmt: skip
    bench = subprocess.run(command, capture_output=True, text=True, timeout=560)
    assert bench.returncode == 0, bench.stdout + bench.stderr
    report = json.loads(out.read_text())
    assert (report["specimen"], report["focus_mode"]) == ("phase-cells", "valley")
    score = report["scores"]["kf-2d-lean"]
    cells = SimulatorOptions(seed=1, rows=4, cols=4, width=128, height=128, specimen="phase-cells")
    glass = bare_glass(cells, "slide-0")
    assert (score["empty_tiles"], score["tissue_tiles"]) == (glass.sum(), 16 - glass.sum())
    assert score["tissue_in_focus_fraction"] == 1.0
    assert 0.0 < score["tissue_mae_um"] < 0.3  # in focus: within 0.44 um (half the DOF)
    assert score["seam_error_px"] is None and score["tiles_focused_on_dust"] == 0
    assert score["empty_tiles_frames"] == 1.0
    planes = 11  # `focustrack scan --phase-planes`' default
    assert score["tiles_with_phase"] == score["tissue_tiles"]
    assert score["phase_frames_per_tile"] == planes * score["tissue_tiles"] / 16
    assert "focus mode valley" in bench.stdout


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--family", "bogus"], "argument --family: invalid choice: 'bogus'"),
        (["--specimen", "tissues"], "argument --specimen: invalid choice: 'tissues'"),
        (["--focus-mode", "min"], "argument --focus-mode: invalid choice: 'min'"),
        (["--strategies", "kf-2d", "nope"], "argument --strategies: invalid choice: 'nope'"),
        (["--overlap", "0.9"], "error: --overlap: Input should be less than 0.5"),
        (["--size", "65"], "error: --size must be even"),
        (["--size", "62"], "argument --size: must be in [64, 16384], got 62"),
        (["--rows", "1"], "argument --rows: must be in [2, 1000], got 1"),
    ],
)
def test_a_slide_the_bench_cannot_scan_is_refused_before_any_service_starts(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        status = main(["bench", "slide", "--out", str(tmp_path / "out"), *argv])
    except SystemExit as exit_:  # argparse's own refusals
        status = exit_.code
    assert status == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "seed-1").exists()  # no stack was started
