"""`focustrack scan --phase` end to end on loopback: a Zenoh router (this process), the
instrument, focus, estimator and phase services and the scan, each a real process; the
OME-Zarr gets the phase in radians beside the mosaic, and a scan without --phase none."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zarr

from focustrack.demo import PHASE_PASS_TILES, phase_pass
from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire.trust import new_nonce
from focustrack_scheduler import outputs
from focustrack_scheduler.clients import InstrumentClient
from focustrack_scheduler.settings import ScanOptions

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

ROWS = COLS = 2
SIZE = 128
#: The slide's field of plasma alone (the stained smear of seed 3): nothing in view.
EMPTY_TILE = (0, 0)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    instrument_args = [
        "--seed", "3", "--slides", "1", "--rows", str(ROWS), "--cols", str(COLS),
        "--width", str(SIZE), "--height", str(SIZE),
    ]  # fmt: skip
    with LocalStack(tmp_path_factory.mktemp("stack"), instrument_args, phase=True) as running:
        yield running


def takes_phase_stacks(stack: LocalStack) -> bool:
    """Whether the instrument takes a phase stack as one (its header says so)."""
    assert stack.session is not None
    request = instrument_pb2.AcquireRequest(
        slide=SLIDE, row=0, col=0, z_low_um=0.0, z_step_um=0.5, n_frames=2,
        sequence=1 << 50, nonce=new_nonce(), reference_z_um=0.25,
        purpose=instrument_pb2.ACQUISITION_PURPOSE_PHASE,
    )  # fmt: skip
    reply = InstrumentClient(stack.session, INSTRUMENT).acquire(request)
    return reply.header.purpose == instrument_pb2.ACQUISITION_PURPOSE_PHASE


def scan_command(stack: LocalStack, out_dir: Path, *extra: str) -> list[str]:
    """`focustrack scan` on the stack's slide, its results checked with the stack's key."""
    return [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack.estimator_url, "--connect", stack.endpoint,
        "--instrument", INSTRUMENT, "--slide", SLIDE, "--out", str(out_dir),
        "--result-key-file", str(stack.result_key_file), *extra,
    ]  # fmt: skip


def scan(stack: LocalStack, out_dir: Path, *extra: str) -> dict:
    """Run `focustrack scan` on the stack's slide; its report."""
    done = subprocess.run(
        scan_command(stack, out_dir, *extra),
        capture_output=True,
        text=True,
        timeout=300,
        env=os.environ,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads((out_dir / outputs.REPORT).read_text())


def logged(out_dir: Path, event: str) -> list[dict]:
    lines = (out_dir / outputs.LOG_FILE).read_text().splitlines()
    return [entry for entry in map(json.loads, lines) if entry["event"] == event]


def found_empty(out_dir: Path) -> set[tuple[int, int]]:
    """The tiles whose stacks the focus service found empty (nothing in view)."""
    return {(e["row"], e["col"]) for e in logged(out_dir, "measured") if "empty" in e["flags"]}


def test_scan_phase_writes_the_phase_in_radians_beside_the_mosaic(
    stack: LocalStack, tmp_path: Path
) -> None:
    """Every tile with something in view gets its phase, in radians, in the OME-Zarr beside
    the mosaic; the smear's one field of plasma alone (seed 3, tile (0, 0)) takes no phase
    stack, and its place in the phase image is NaN."""
    if not takes_phase_stacks(stack):
        pytest.skip("this instrument takes phase stacks as focus stacks (it predates them)")
    report = scan(stack, tmp_path, "--phase", "--phase-planes", "7")
    assert report["tiles_imaged"] == ROWS * COLS
    assert found_empty(tmp_path) == {EMPTY_TILE}
    assert report["tiles_with_phase"] == ROWS * COLS - 1
    assert report["phase_images_acquired"] == 7 * (ROWS * COLS - 1)
    assert EMPTY_TILE not in {(e["row"], e["col"]) for e in logged(tmp_path, "phase")}
    kept = {(e["row"], e["col"]): e["z_um"] for e in logged(tmp_path, "kept")}
    for entry in logged(tmp_path, "phase"):  # each centred on the z the tile is imaged at
        assert entry["error"] is None and entry["n_frames"] == 7
        assert 0.0 <= entry["background_share"] <= 1.0  # the share of the tile taken as glass
        assert entry["reference_z_um"] == kept[(entry["row"], entry["col"])]
    root = zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r")
    phase = root[outputs.ZARR_PHASE]
    assert phase.attrs["focustrack"] == {"layer": "phase", "unit": "radian"}
    (channel,) = phase.attrs["ome"]["omero"]["channels"]
    assert channel["label"] == "phase (rad)" and channel["window"]["end"] == pytest.approx(math.pi)
    mosaic_pixels = root["s0"].shape[1:]
    pixels = np.asarray(phase["s0"])
    assert pixels.shape == (1, *mosaic_pixels) and pixels.dtype == np.float32
    tiles = pixels[0].reshape(ROWS, SIZE, COLS, SIZE).transpose(0, 2, 1, 3)
    assert np.isnan(tiles[EMPTY_TILE]).all()  # no phase taken: none shown
    phased = np.ones((ROWS, COLS), dtype=bool)
    phased[EMPTY_TILE] = False
    assert np.isfinite(tiles[phased]).all() and np.abs(tiles[phased]).max() <= math.pi + 1e-5
    assert (tiles[phased].std(axis=(1, 2)) > 0).all()  # every other tile holds a phase image
    # the same placement as the mosaic's: same pixel size and origin
    transforms = phase.attrs["ome"]["multiscales"][0]["datasets"][0]["coordinateTransformations"]
    mosaic = root.attrs["ome"]["multiscales"][0]["datasets"][0]["coordinateTransformations"]
    assert transforms == mosaic


def test_a_scan_killed_before_its_phase_results_came_takes_them_when_resumed(
    stack: LocalStack, tmp_path: Path
) -> None:
    """SIGKILL once the first tile is kept (its phase stack is yet to come back), then the
    same command: every tile ends with its phase. The tiles the killed run kept without
    phase used to stay without it, and nothing said so."""
    if not takes_phase_stacks(stack):
        pytest.skip("this instrument takes phase stacks as focus stacks (it predates them)")
    first = subprocess.Popen(
        scan_command(stack, tmp_path, "--phase", "--phase-planes", "5"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline_s = time.monotonic() + 120
    while not (tmp_path / outputs.LOG_FILE).exists() or not logged(tmp_path, "kept"):
        assert first.poll() is None, "the scan ended before it kept a tile"
        assert time.monotonic() < deadline_s, "the scan kept no tile"
        time.sleep(0.01)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    report = scan(stack, tmp_path, "--phase", "--phase-planes", "5")
    assert report["tiles_imaged"] == ROWS * COLS
    with_phase = {(e["row"], e["col"]) for e in logged(tmp_path, "phase") if e["file"]}
    tiles = {(row, col) for row in range(ROWS) for col in range(COLS)}
    # Every tile but one found empty: the field of plasma, where the log says so (a run
    # killed after posting its stack and before logging it takes its phase when resumed,
    # as any tile's left without).
    assert found_empty(tmp_path) <= {EMPTY_TILE}
    assert with_phase == tiles - found_empty(tmp_path)
    assert report["tiles_with_phase"] == len(with_phase)


def test_a_scan_without_phase_takes_no_phase_stack(stack: LocalStack, tmp_path: Path) -> None:
    report = scan(stack, tmp_path)
    assert report["tiles_imaged"] == ROWS * COLS
    assert report["tiles_with_phase"] == report["phase_images_acquired"] == 0
    assert report["wall_time_s"]["phase_s"] == 0
    assert logged(tmp_path, "phase") == []
    assert not (tmp_path / outputs.PHASE).exists()
    assert outputs.ZARR_PHASE not in zarr.open_group(tmp_path / outputs.MOSAIC_ZARR, mode="r")


def test_the_demo_s_phase_pass_recovers_the_true_phase_of_unstained_cells(
    tmp_path: Path,
) -> None:
    """Unstained red cells: focus on the contrast minimum, a phase stack centred on each
    tile's predicted focus, and the phase that comes back is the simulator's.

    Seed 0 has a tile of bare glass among the cells (row 1, column 1): it is found empty
    and takes no phase stack; its neighbours after it are looked at first, and the look
    must not take their cells for glass."""
    args = argparse.Namespace(seed=0, size=256)
    flags = argparse.Namespace(phase=True, no_progress=True)
    options = ScanOptions.from_args(flags, environment=False)
    report, scores = phase_pass(args, options, tmp_path, live=None)
    tiles = PHASE_PASS_TILES * PHASE_PASS_TILES
    assert report["in_focus_fraction"] == 1.0
    assert report["tiles_flagged"].get("empty", 0) == 1  # the bare glass alone
    # the slide's curve read as a valley's reciprocal: 7.3 focus frames a tile (9.7 when it
    # was learnt as a peak where the curve has its minimum)
    assert report["images_per_tile"] < 8.5
    assert report["tiles_with_phase"] == tiles - 1  # none of the bare glass
    assert scores.bare_glass_tiles == 0 and len(scores.correlations) == tiles - 1
    assert min(scores.correlations) > 0.9, scores.correlations  # 0.97-0.98 measured
    # Every tile's phase is anchored to its glass, so the tiles share their zero.
    assert len(scores.glass_rad) == tiles - 1
    # measured: 15 tiles within 0.02 rad, one at 0.054 (row 0, column 1)
    glass_rad = np.abs(scores.glass_rad)
    assert np.median(glass_rad) < 0.02 and glass_rad.max() < 0.1, scores.glass_rad


def test_phase_stacks_beyond_the_instrument_s_frame_limit_are_cut_and_said_once(
    stack: LocalStack, tmp_path: Path
) -> None:
    """They were cut to the camera's limit without a word."""
    if not takes_phase_stacks(stack):
        pytest.skip("this instrument takes phase stacks as focus stacks (it predates them)")
    done = subprocess.run(
        scan_command(stack, tmp_path, "--phase", "--phase-planes", "500"),
        capture_output=True, text=True, timeout=300, env=os.environ, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    taken = {entry["n_frames"] for entry in logged(tmp_path, "phase")}
    assert len(taken) == 1 and taken.pop() < 500
    assert done.stderr.count("phase stacks of 500 planes (--phase-planes) are cut to") == 1
