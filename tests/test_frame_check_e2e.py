"""End to end on loopback: the second pass's first-frame check through the real services (a
simulated instrument with a virtual tissue slide, the focus and estimator services, each a
real process, and `focustrack scan --first-pass`).

The first pass's map is handed to the second pass with one tile moved 0.7 um (the slide
changed there, which the map does not know): the rule images that tile once at its
prediction, the scheduler finds the frame less sharp than the first pass's image of the
tile, posts it out of focus, the estimator asks for a stack of the tile, and the tile ends
in focus. With the check off (`--frame-check-ratio 0`) the same tile is imaged once, out of
focus."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from focustrack.local_stack import LocalStack
from focustrack_core.geometry import ScanGrid
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_scheduler import outputs

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

SIDE = 4
SIZE = 128
SEED = 3
#: The slide moved on the stage between the passes (x, y) um, and in z.
LATERAL_UM = (2.5, 1.5)
AXIAL_UM = 4.0
#: The tile the map is wrong about, and by how much, um (about 5 of its predicted sigmas):
#: the second row's first, where the pass, imaged once a tile since its start, is still
#: sure enough to image it once (by the last tile, with no stack since the first row,
#: kf-rescan is unsure enough to take a stack anyway, and the check has nothing to do).
MOVED = ScanGrid(SIDE, SIDE).serpentine[4]
MOVED_UM = 0.7


def scan(stack: LocalStack, out_dir: Path, strategy: str, *extra: str) -> dict:
    command = [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack.estimator_url, "--connect", stack.endpoint,
        "--instrument", "sim", "--slide", "slide-0", "--strategy", strategy,
        "--out", str(out_dir), *extra,
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads((out_dir / outputs.REPORT).read_text())


def log_of(out_dir: Path, tile: tuple[int, int]) -> list[dict]:
    """The scan log's acquisitions and measurements of `tile`, in order."""
    lines = (out_dir / outputs.LOG_FILE).read_text().splitlines()
    return [
        e
        for e in map(json.loads, lines)
        if e["event"] in ("acquired", "measured") and (e["row"], e["col"]) == tile
    ]


def test_a_frame_less_sharp_than_the_first_passs_gets_its_tile_measured(tmp_path: Path) -> None:
    instrument_args = [
        "--seed", str(SEED), "--slides", "1", "--rows", str(SIDE), "--cols", str(SIDE),
        "--width", str(SIZE), "--height", str(SIZE), "--tissue-slide",
    ]  # fmt: skip
    tile = (MOVED.row, MOVED.col)
    with LocalStack(tmp_path / "stack", instrument_args) as stack:
        first_dir = tmp_path / "first"
        scan(stack, first_dir, "kf-2d-lean")
        table = np.load(first_dir / outputs.FOCUS_MAP_NPY)
        prior_um = table["smoothed_um"].copy()
        prior_um[tile] -= MOVED_UM
        stack.restart_with("instrument", [
            "--lateral-offset-x-um", str(LATERAL_UM[0]),
            "--lateral-offset-y-um", str(LATERAL_UM[1]), "--z-offset-um", str(AXIAL_UM),
        ])  # fmt: skip
        sigma_um = table["smoothed_sigma_um"]
        second = [
            "--param", f"prior_map_um={json.dumps(prior_um.ravel().tolist())}",
            "--param", f"prior_map_sigma_um={json.dumps(sigma_um.ravel().tolist())}",
            "--first-pass", str(first_dir), "--lateral-tiles", "2",
        ]  # fmt: skip
        unchecked = ["--frame-check-ratio", "0"]
        reports = {
            checked: scan(
                stack,
                tmp_path / str(checked),
                "kf-rescan",
                *second,
                *([] if checked else unchecked),
            )
            for checked in (True, False)
        }
        assert stack.session is not None
        truth = rpc.call(
            stack.session, keys.truth_key("sim", "slide-0"), instrument_pb2.AcquireRequest(),
            instrument_pb2.SlideTruth, 5.0,
        )  # fmt: skip
    focus_um = np.array(truth.best_focus_um).reshape(SIDE, SIDE)
    dof_um = reports[True]["dof_um"]
    for checked, report in reports.items():
        assert report["tiles_imaged"] == SIDE * SIDE
        events = log_of(tmp_path / str(checked), tile)
        first, posted = events[0], events[1]
        assert first["event"] == "acquired" and first["n_frames"] == 1  # once, predicted
        assert posted["event"] == "measured" and posted["z_um"] is None
        z_used_um = np.load(tmp_path / str(checked) / outputs.FOCUS_MAP_NPY)["z_used_um"]
        error_um = abs(z_used_um.reshape(SIDE, SIDE)[tile] - focus_um[tile])
        if checked:  # found out of focus: a stack of the tile followed, measured
            assert posted.get("frame_out_of_focus") is True
            stacks = [e for e in events[2:] if e["event"] == "acquired"]
            assert stacks and stacks[0]["n_frames"] > 1
            assert any(e["event"] == "measured" and e["z_um"] is not None for e in events[2:])
            assert error_um <= dof_um / 2
        else:  # imaged once at the map's wrong height
            assert "frame_out_of_focus" not in posted and len(events) == 2
            assert error_um > dof_um / 2
