"""The scan's record, part by part: log, state, tally, mosaic store, listeners, in-focus score."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from focustrack_core.domain import Acquisition, Measurement, Outcome, Purpose, ZRange
from focustrack_core.fusion import fuse_planes
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler import outputs
from focustrack_scheduler.in_focus import InFocusScore
from focustrack_scheduler.listeners import Listeners
from focustrack_scheduler.mosaic_store import MosaicStore, to_uint8
from focustrack_scheduler.outputs import OutputFolderError
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.scan_log import ScanLog
from focustrack_scheduler.scan_state import ScanState
from focustrack_scheduler.tally import ScanTally

GRID = ScanGrid(2, 3)
TILE_PX = 4
BIT_DEPTH = 12


def image(value: int) -> np.ndarray:
    """A tile image (h, w, 3) of 12-bit camera values."""
    return np.full((TILE_PX, TILE_PX, 3), value, dtype=np.uint16)


def test_the_log_reads_back_what_it_appended_and_survives_a_line_cut_short(
    tmp_path: Path,
) -> None:
    path = tmp_path / outputs.LOG_FILE
    log = ScanLog(path)
    log.append({"event": "kept", "row": 0, "col": 1, "z_um": 1.5})
    assert json.loads(path.read_text()) == {"event": "kept", "row": 0, "col": 1, "z_um": 1.5}
    log.close()
    with path.open("a") as file:  # a kill in the middle of the next line
        file.write('{"event": "kept", "row": 1,')
    again = ScanLog(path)
    assert list(again.read()) == [{"event": "kept", "row": 0, "col": 1, "z_um": 1.5}]
    again.append({"event": "kept", "row": 1, "col": 1, "z_um": 2.0})  # on a line of its own
    again.close()
    assert [entry["row"] for entry in ScanLog(path).read()] == [0, 1]


def test_the_state_is_merged_and_written_whole(tmp_path: Path) -> None:
    state = ScanState(tmp_path / outputs.STATE_FILE)
    assert state.read() is None
    state.save(strategy="kf-2d", slide="slide-0")
    state.save(slide_id="abc", slide="slide-1")
    assert state.read() == {"strategy": "kf-2d", "slide": "slide-1", "slide_id": "abc"}
    assert [path.name for path in tmp_path.iterdir()] == [outputs.STATE_FILE]  # no .tmp left


@pytest.mark.parametrize(
    ("text", "why"),
    [("[1,2", "it is not JSON"), ("[1, 2]", "it holds a JSON list, not an object")],
)
def test_a_damaged_state_is_named_not_merged_into(tmp_path: Path, text: str, why: str) -> None:
    state = ScanState(tmp_path / outputs.STATE_FILE)
    state.path.write_text(text)
    for attempt in (state.read, lambda: state.save(slide_id="abc")):
        with pytest.raises(OutputFolderError, match=f"scan.json is damaged: {why}.*move it away"):
            attempt()
    assert state.path.read_text() == text


def test_the_tally_folds_the_log_entries() -> None:
    tally = ScanTally()
    entries: list[dict[str, Any]] = [
        {"event": "acquired", "row": 0, "col": 0, "purpose": "scan", "n_frames": 5,
         "scan_time_s": 1.0},
        {"event": "acquired", "row": 0, "col": 0, "purpose": "retry", "n_frames": 3,
         "scan_time_s": 0.5},
        {"event": "measured", "row": 0, "col": 0, "z_um": 1.0},
        {"event": "measured", "row": 0, "col": 0, "z_um": 1.2},
        {"event": "kept", "row": 0, "col": 0, "z_um": 1.25},
        {"event": "planes", "row": 0, "col": 0, "z_um": [1.0, 1.25, 1.5]},
        {"event": "acquired", "row": 1, "col": 2, "purpose": "scan", "n_frames": 7,
         "scan_time_s": 2.0},
        {"event": "kept", "row": 1, "col": 2, "z_um": -0.5},
        {"event": "from a newer version", "row": 0, "col": 0},
    ]  # fmt: skip
    for entry in entries:
        tally.take(entry)
    assert (tally.n_images, tally.scan_time_s, tally.frames_kept) == (15, 3.5, 4)
    assert tally.measured[(0, 0)]["z_um"] == 1.2  # the last measurement of the tile
    assert tally.planes == {(0, 0): [1.0, 1.25, 1.5]}
    np.testing.assert_array_equal(tally.images_per_tile(GRID), [[8, 0, 0], [0, 0, 7]])
    z_kept_um = tally.z_kept_um(GRID)
    assert (z_kept_um[0, 0], z_kept_um[1, 2]) == (1.25, -0.5)
    assert np.isnan(z_kept_um).sum() == GRID.n_tiles - 2
    with pytest.raises(KeyError):
        tally.take({"event": "kept", "row": 0})


def test_a_tile_only_imaged_is_not_a_tile_without_focus() -> None:
    """An image-only acquisition (one frame at a sure prediction, or more frames to keep)
    posts no best focus: it is not a stack that found none. It used to be counted among
    the tiles without focus, and the summary warned of most tiles of a good lean scan."""
    tally = ScanTally()
    entries: list[dict[str, Any]] = [
        # one frame at the prediction
        {"event": "measured", "row": 0, "col": 0, "measure": False, "z_um": None, "flags": []},
        # measured, then more frames to keep
        {"event": "measured", "row": 0, "col": 1, "measure": True, "z_um": 0.4, "flags": []},
        {"event": "measured", "row": 0, "col": 1, "measure": False, "z_um": None, "flags": []},
        # empty glass: found none
        {"event": "measured", "row": 1, "col": 0, "measure": True, "z_um": None,
         "flags": ["empty", "flat"]},
        # one frame at the prediction, read as a look (a phase scan): glass
        {"event": "measured", "row": 0, "col": 2, "measure": False, "z_um": None,
         "flags": ["empty", "flat"]},
        # a log from before the field: every entry measured, as before
        {"event": "measured", "row": 1, "col": 1, "z_um": None, "flags": ["flat"]},
    ]  # fmt: skip
    for entry in entries:
        tally.take(entry)
    assert tally.tiles_without_focus() == [(1, 0), (1, 1)]
    assert tally.flag_counts() == {"empty": 1, "flat": 2}
    assert tally.tiles_found_empty() == {(1, 0), (0, 2)}  # glass: no phase stack to take
    assert tally.focus_measured[(0, 1)]["z_um"] == 0.4  # the best focus posted for it
    assert tally.measured[(0, 1)]["z_um"] is None  # its last post, as logged


def test_the_mosaic_store_places_tiles_keeps_planes_and_carries_on_after_a_restart(
    tmp_path: Path,
) -> None:
    store = MosaicStore(tmp_path)
    assert store.read() is None
    store.write_tile(GRID, 1, 2, image(4095), BIT_DEPTH)
    planes = np.stack([image(0), image(1000), image(4095)])
    assert store.save_planes(GRID, 0, 0, planes, BIT_DEPTH) == "planes/r0_c0.npy"
    np.testing.assert_array_equal(np.load(tmp_path / "planes" / "r0_c0.npy"), planes)
    store.close()

    again = MosaicStore(tmp_path)  # a restarted scheduler: the tiles already kept stay
    again.write_tile(GRID, 0, 1, image(2048), BIT_DEPTH)
    mosaic = again.read()
    assert mosaic is not None and mosaic.shape == (2 * TILE_PX, 3 * TILE_PX, 3)
    np.testing.assert_array_equal(mosaic[TILE_PX:, 2 * TILE_PX :], 255)
    np.testing.assert_array_equal(mosaic[:TILE_PX, TILE_PX : 2 * TILE_PX], 128)
    fused = to_uint8(fuse_planes(planes), BIT_DEPTH)
    np.testing.assert_array_equal(mosaic[:TILE_PX, :TILE_PX], fused)
    assert not mosaic.flags.writeable
    with pytest.raises(ValueError, match="use a new output folder"):
        MosaicStore(tmp_path).write_tile(GRID, 0, 0, np.zeros((8, 8, 3)), BIT_DEPTH)


def _cut_short(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-7])


def _garbled(path: Path) -> None:
    path.write_bytes(b"not an npy file at all" * 4)


def _of_floats(path: Path) -> None:
    np.save(path, np.zeros((2 * TILE_PX, 3 * TILE_PX, 3), np.float32))


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        (_cut_short, "it has 409 bytes, where its header promises 416"),
        (_garbled, "its header cannot be read"),
        (_of_floats, "it holds float32"),
    ],
)
def test_a_damaged_partial_mosaic_is_named_not_written_into(
    tmp_path: Path, damage: Any, why: str
) -> None:
    """An earlier run's partial mosaic cut short, garbled or of another type is a
    OutputFolderError that says so and what to do, before a tile is written; a file cut short
    used to be mapped all the same (a tile written past its end kills the process)."""
    store = MosaicStore(tmp_path)
    store.write_tile(GRID, 0, 0, image(100), BIT_DEPTH)
    store.close()
    store.check()  # whole
    damage(store.path)
    resumed = MosaicStore(tmp_path)
    for attempt in (
        resumed.check,
        lambda: resumed.write_tile(GRID, 1, 2, image(7), BIT_DEPTH),
        lambda: resumed.tile(GRID, 0, 0),
    ):
        with pytest.raises(OutputFolderError, match=f"is damaged: {why}.*move it away"):
            attempt()


def test_a_partial_mosaic_of_another_grid_is_refused(tmp_path: Path) -> None:
    store = MosaicStore(tmp_path)
    store.write_tile(GRID, 0, 0, image(100), BIT_DEPTH)
    store.close()
    with pytest.raises(OutputFolderError, match="use a new output folder"):
        MosaicStore(tmp_path).write_tile(ScanGrid(3, 3), 0, 0, image(100), BIT_DEPTH)


def test_listeners_are_called_in_the_order_they_came() -> None:
    listeners = Listeners()
    heard: list[tuple[str, dict[str, Any]]] = []
    listeners.notify({"event": "before"})  # nobody yet
    listeners.add(lambda entry: heard.append(("first", entry)))
    listeners.add(lambda entry: heard.append(("second", entry)))
    listeners.notify({"event": "kept"})
    assert heard == [("first", {"event": "kept"}), ("second", {"event": "kept"})]


def test_a_tile_is_in_focus_when_its_image_or_one_of_its_planes_is() -> None:
    truth_um = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    score = InFocusScore(truth_um, dof_um=1.0)
    kept = {(0, 0): 0.4, (0, 1): 1.6, (0, 2): 2.6, (1, 1): 4.0}
    assert score.tiles({}, {}) == 0
    assert score.tiles(kept, {}) == 2  # (0, 0) and (1, 1) within 0.5 um
    assert score.tiles(kept, {(0, 1): [1.2, 1.6]}) == 3  # a plane of (0, 1) is
    assert score.tiles(kept, {(0, 0): [-1.0, 0.4]}) == 2  # already in focus: counted once
    assert InFocusScore(truth_um, dof_um=4.0).tiles(kept, {}) == 4


def test_the_record_logs_tallies_and_tells_its_listeners_and_is_read_back(
    tmp_path: Path,
) -> None:
    record = ScanRecord(tmp_path)
    heard: list[str] = []
    record.listeners.add(lambda entry: heard.append(entry["event"]))
    acquisition = Acquisition(7, 1, 2, ZRange(-1.0, 0.5, 5), Purpose.SCAN, True)
    record.acquired(acquisition, 5, 1.5)
    outcome = Outcome(1, 2, True, posterior_um=0.1, posterior_sigma_um=float("nan"))
    record.measurement(acquisition, Measurement(0.0, 0.05), outcome, ([0.0], [1.0]))
    record.keep(GRID, 1, 2, 0.0, image(100), BIT_DEPTH)
    record.keep_planes(GRID, 1, 2, [-0.5, 0.0], np.stack([image(0), image(100)]), BIT_DEPTH)
    record.state.save(slide_id="abc")
    assert heard == ["acquired", "measured", "kept", "planes"]
    record.close()

    logged = [json.loads(line) for line in (tmp_path / outputs.LOG_FILE).read_text().splitlines()]
    assert logged[1] == {
        "event": "measured", "row": 1, "col": 2, "sequence": 7, "measure": True, "z_um": 0.0,
        "sigma_um": 0.05, "flags": [], "posterior_um": 0.1, "posterior_sigma_um": None,
        "curve_z_um": [0.0], "curve_scores": [1.0],
    }  # fmt: skip
    assert logged[3]["file"] == "planes/r1_c2.npy"
    again = ScanRecord(tmp_path)  # a restarted scheduler reads the record back
    assert again.tally.kept == {(1, 2): 0.0} and again.tally.planes == {(1, 2): [-0.5, 0.0]}
    assert again.tally.n_images == 5 and again.state.read() == {"slide_id": "abc"}
    again.close()
