"""End to end on loopback: a drifting simulated instrument (settling and a random walk) with a
laser autofocus, the focus and estimator services and `focustrack scan`, each a real process:
with a time state the estimator asks for revisits (`purpose: revisit` in `/next`), which the
scheduler makes and posts; `kf-2d-laser` asks for a laser reading on every tile, which the
scheduler takes from the instrument's laser queryable; every tile is imaged once."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import httpx
import numpy as np
import pytest

from focustrack.local_stack import LocalStack
from focustrack_core.drift import ThermalDrift
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_scheduler import outputs

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

ROWS = COLS = 6
SIZE = 128
SEED = 3
#: The instrument's drift: 3 um settling (tau 5 s) and a walk of 1.5 um per sqrt(minute).
DRIFT = ThermalDrift(settle_um=3.0, settle_tau_s=5.0, walk_um_per_sqrt_min=1.5, seed=SEED)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    instrument_args = [
        "--seed", str(SEED), "--slides", "1", "--rows", str(ROWS), "--cols", str(COLS),
        "--width", str(SIZE), "--height", str(SIZE), "--drift-settle-um", "3",
        "--drift-settle-tau-s", "5", "--drift-walk-um-per-sqrt-min", "1.5", "--laser",
    ]  # fmt: skip
    with LocalStack(tmp_path_factory.mktemp("stack"), instrument_args) as running:
        yield running


def scan(
    stack: LocalStack, out_dir: Path, strategy: str, *params: str, extra: Sequence[str] = ()
) -> dict:
    command = [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack.estimator_url, "--connect", stack.endpoint,
        "--instrument", "sim", "--slide", "slide-0", "--strategy", strategy,
        "--out", str(out_dir), *[arg for p in params for arg in ("--param", p)], *extra,
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads((out_dir / outputs.REPORT).read_text())


def in_focus_when_imaged(stack: LocalStack, out_dir: Path, dof_um: float) -> float:
    """The share of tiles whose image lies within dof/2 of the focus when it was taken.

    The scan's report judges images against the truth at its end; with a drift, a tile's
    truth is the slide's focus plus the drift at the start of the tile's last stack (the
    log's durations, summed back from the instrument's clock now)."""
    assert stack.session is not None
    truth = rpc.call(
        stack.session, keys.truth_key("sim", "slide-0"), instrument_pb2.AcquireRequest(),
        instrument_pb2.SlideTruth, 5.0,
    )  # fmt: skip
    focus_um = np.array(truth.best_focus_um).reshape(ROWS, COLS) - truth.drift_um
    acquired = logged(out_dir)
    starts_s = truth.clock_s - np.cumsum([e["scan_time_s"] for e in acquired][::-1])[::-1]
    imaged_s = {}
    for entry, start_s in zip(acquired, starts_s, strict=True):
        if entry["purpose"] != "revisit":
            imaged_s[(entry["row"], entry["col"])] = start_s
    z_used_um = np.load(out_dir / outputs.FOCUS_MAP_NPY)["z_used_um"].reshape(ROWS, COLS)
    in_focus = [
        abs(z_used_um[tile] - focus_um[tile] - DRIFT.at(t_s)) <= dof_um / 2
        for tile, t_s in imaged_s.items()
    ]
    return float(np.mean(in_focus))


def logged(out_dir: Path) -> list[dict]:
    lines = (out_dir / outputs.LOG_FILE).read_text().splitlines()
    return [entry for entry in map(json.loads, lines) if entry["event"] == "acquired"]


def test_a_drifting_scan_revisits_tiles_through_the_services(
    http: httpx.Client, stack: LocalStack, tmp_path: Path
) -> None:
    report = scan(
        stack, tmp_path, "kf-2d-lean",
        "drift_walk_um2_per_s=0.04", "drift_rate_sigma_um_per_s=0.3",
        "drift_settle_tau_s=5", "revisit_drift_share=0.2",
    )  # fmt: skip
    assert report["tiles_imaged"] == ROWS * COLS
    acquired = logged(tmp_path)
    revisits = [e for e in acquired if e["purpose"] == "revisit"]
    assert revisits, "no revisit was asked for"
    first_seen = {}
    for entry in acquired:
        first_seen.setdefault((entry["row"], entry["col"]), entry["sequence"])
    for entry in revisits:  # a tile measured before, with a short stack
        assert first_seen[(entry["row"], entry["col"])] < entry["sequence"]
        assert entry["n_frames"] == 3
    slide = http.get(f"{stack.estimator_url}/v1/slides/{report['estimator_slide_id']}").json()
    assert slide["done"] is True
    # a drift of 0.6 um/s at the start: most tiles, not all, in focus when imaged
    assert in_focus_when_imaged(stack, tmp_path, report["dof_um"]) >= 0.8


def test_a_laser_scan_reads_every_tile_and_images_most_once(
    stack: LocalStack, tmp_path: Path
) -> None:
    report = scan(stack, tmp_path, "kf-2d-laser")
    assert report["tiles_imaged"] == ROWS * COLS
    acquired = logged(tmp_path)
    readings = [e for e in acquired if e["purpose"] == "laser"]
    assert sorted((e["row"], e["col"]) for e in readings) == [
        (row, col) for row in range(ROWS) for col in range(COLS)
    ]
    assert all(e["n_frames"] == 0 and e["scan_time_s"] > 0 for e in readings)
    # the first tiles learn the offset from the glass with stacks; then single frames
    assert report["images_acquired"] < 4 * ROWS * COLS
    single = [e for e in acquired if e["purpose"] == "scan" and e["n_frames"] == 1]
    assert len(single) >= ROWS * COLS / 3
    assert in_focus_when_imaged(stack, tmp_path, report["dof_um"]) >= 0.8


#: The second pass's slide, moved on the stage between the passes (x, y) um and in z.
LATERAL_UM = (2.5, 1.5)
AXIAL_UM = 4.0


def test_a_second_pass_lands_its_tiles_where_the_first_passs_were(tmp_path: Path) -> None:
    """A virtual tissue slide scanned, then moved by a few um in x, y and z (the instrument
    restarted with it): the second pass (`kf-rescan`, the first's map, `--first-pass`) finds
    the offset from its first tiles, takes those again at it, and every tile's final image
    is taken within half a pixel of the place of the first pass's (the simulator's truth:
    where the stage went, less where the slide lies)."""
    instrument_args = [
        "--seed", str(SEED), "--slides", "1", "--rows", "4", "--cols", "4",
        "--width", str(SIZE), "--height", str(SIZE), "--tissue-slide",
    ]  # fmt: skip
    with LocalStack(tmp_path / "stack", instrument_args) as lateral_stack:
        first_dir, second_dir = tmp_path / "first", tmp_path / "second"
        scan(lateral_stack, first_dir, "kf-2d-lean")
        table = np.load(first_dir / outputs.FOCUS_MAP_NPY)
        lateral_stack.restart_with("instrument", [
            "--lateral-offset-x-um", str(LATERAL_UM[0]),
            "--lateral-offset-y-um", str(LATERAL_UM[1]), "--z-offset-um", str(AXIAL_UM),
        ])  # fmt: skip
        report = scan(
            lateral_stack, second_dir, "kf-rescan",
            f"prior_map_um={json.dumps(table['smoothed_um'].ravel().tolist())}",
            f"prior_map_sigma_um={json.dumps(table['smoothed_sigma_um'].ravel().tolist())}",
            extra=["--first-pass", str(first_dir), "--lateral-tiles", "2"],
        )  # fmt: skip
        assert lateral_stack.session is not None
        truth = rpc.call(
            lateral_stack.session, keys.truth_key("sim", "slide-0"),
            instrument_pb2.AcquireRequest(), instrument_pb2.SlideTruth, 5.0,
        )  # fmt: skip
    assert (truth.lateral_offset_x_um, truth.lateral_offset_y_um) == LATERAL_UM
    assert report["tiles_imaged"] == 16
    retaken = [e for e in logged(second_dir) if e["purpose"] == "retake"]
    assert retaken, "the tiles imaged before the offset was known were not taken again"
    first_places, second_places = final_places(first_dir), final_places(second_dir)
    assert set(second_places) == set(first_places) and len(second_places) == 16
    pixel_um = json.loads((second_dir / outputs.STATE_FILE).read_text())["tile"]["pixel_size_um"]
    for tile, (x_um, y_um) in second_places.items():
        first_x_um, first_y_um = first_places[tile]
        # the slide's place under the camera, against the first pass's
        error_px = (
            np.hypot(x_um - LATERAL_UM[0] - first_x_um, y_um - LATERAL_UM[1] - first_y_um)
            / pixel_um
        )
        assert error_px <= 0.5, (tile, error_px)


def final_places(out_dir: Path) -> dict[tuple[int, int], tuple[float, float]]:
    """Where the stage stood (x, y) um for each tile's final image, from the scan's log."""
    lines = (out_dir / outputs.LOG_FILE).read_text().splitlines()
    kept = [e for e in map(json.loads, lines) if e["event"] == "kept"]
    return {(e["row"], e["col"]): (e["stage_x_um"], e["stage_y_um"]) for e in kept}
