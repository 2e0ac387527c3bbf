"""The Bluesky plan on a real RunEngine with ophyd.sim motors, against a real estimator."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import databroker
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import pytest
from bluesky import RunEngine
from bluesky.callbacks import LiveTable
from bluesky.callbacks.best_effort import BestEffortCallback
from event_model import DocumentNames, NumpyEncoder, schema_validators
from matplotlib.backends.backend_agg import FigureCanvasAgg

from focustrack.lab_sim import SimScope, grid_placement, simulated_ophyd
from focustrack_client import EstimatorClient
from focustrack_client.models import FocusFlag, SlideCreate
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.bluesky import (
    MAP_LAYERS,
    MAP_STREAM,
    PLANES_STREAM,
    STACK_STREAM,
    focustrack_grid,
)
from focustrack_lab.tracker import FocusTracker

matplotlib.use("Agg")  # BestEffortCallback's figures, off screen


def scan(RE: RunEngine, scope: SimScope, tracker: FocusTracker) -> str:
    """Runs the plan over the scope's slide with ophyd.sim devices; the run's uid."""
    camera, x, y, z = simulated_ophyd(scope)
    (run_uid,) = RE(focustrack_grid(camera, x, y, z, tracker, **grid_placement(scope)))
    return str(run_uid)


def events_by_stream(documents: list[tuple[str, dict[str, Any]]]) -> dict[str, list[dict]]:
    """The data of every event document, by the name of its stream."""
    streams = {doc["uid"]: doc["name"] for name, doc in documents if name == "descriptor"}
    events: dict[str, list[dict]] = {}
    for name, doc in documents:
        if name == "event":
            events.setdefault(streams[doc["descriptor"]], []).append(doc["data"])
    return events


def test_a_plan_whose_grid_is_not_the_slide_s_is_refused_before_any_move(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
) -> None:
    """It ran, then stopped at the first tile past the smaller grid (a TileOrderError) or
    put a 3x3 map into a 4x3 signal."""
    tracker = FocusTracker.create(estimator, slide_of(small_scope, "kf-2d", 0.1))
    camera, x, y, z = simulated_ophyd(small_scope)
    RE = RunEngine({})
    documents: list[str] = []
    RE.subscribe(lambda name, _: documents.append(name))
    for rows, pitch_um in ((4, 200.0), (3, 150.0)):
        plan = focustrack_grid(camera, x, y, z, tracker, rows=rows, cols=3, pitch_um=pitch_um)
        with pytest.raises(ValueError, match=r"the plan's grid is .* the estimator's slide"):
            RE(plan)
    assert documents == [] and small_scope.n_frames == 0


@pytest.mark.slow
def test_the_plan_images_every_tile_in_focus_and_the_documents_carry_the_focus_map(
    estimator: EstimatorClient,
    scope: SimScope,
    scope_slide: Callable[[str, float], SlideCreate],
    capsys: pytest.CaptureFixture[str],
) -> None:
    grid = scope.microscope.slides[scope.slide].grid
    dof_um = scope.microscope.spec.optics.depth_of_field_um
    slide = scope_slide("kf-2d", 0.1)
    tracker = FocusTracker.create(estimator, slide)
    documents: list[tuple[str, dict[str, Any]]] = []
    RE = RunEngine({})
    RE.subscribe(lambda name, document: documents.append((name, document)))
    columns = ["focustrack_row", "focustrack_col", "focustrack_z_um", "focustrack_sigma_um"]
    RE.subscribe(LiveTable(columns))  # Bluesky's own callback sees the focus map
    run_uid = scan(RE, scope, tracker)

    names = [name for name, _ in documents]
    assert names[0] == "start" and names[-1] == "stop"
    assert documents[-1][1]["exit_status"] == "success" and documents[-1][1]["run_start"] == run_uid
    events = events_by_stream(documents)
    primary, stacks = events["primary"], events[STACK_STREAM]
    assert len(primary) == grid.n_tiles
    assert len(stacks) == tracker.n_frames
    truth_um, _ = scope.microscope.truth_um(scope.slide)
    for data, tile in zip(primary, grid.serpentine, strict=True):
        assert (data["focustrack_row"], data["focustrack_col"]) == (tile.row, tile.col)
        assert data["z"] == pytest.approx(data["focustrack_z_um"])
        assert abs(data["focustrack_z_um"] - truth_um[tile.row, tile.col]) <= dof_um / 2
        assert np.asarray(data["camera"]).shape == scope.microscope.spec.shape
    # FocusTrack's stacks narrow as it learns: far fewer frames than the first tile's at each.
    assert tracker.n_frames < tracker.tiles[0].n_frames * grid.n_tiles / 2
    # The estimator's map agrees with what the documents said.
    posterior = estimator.focus_map(tracker.slide_id).posterior_um
    for data in primary:
        assert posterior[data["focustrack_row"]][data["focustrack_col"]] == pytest.approx(
            data["focustrack_z_um"]
        )
    table = capsys.readouterr().out
    assert "focustrack_z_um" in table and table.count("|") > grid.n_tiles


@pytest.mark.slow
def test_a_tile_too_unsure_for_one_image_is_read_at_each_of_its_planes(
    estimator: EstimatorClient,
    scope: SimScope,
    scope_slide: Callable[[str, float], SlideCreate],
) -> None:
    grid = scope.microscope.slides[scope.slide].grid
    # A measure whose peak strays 1.5 um from the focus (as the thesis' noise): its sigma says so.
    noisy = FocusSettings(peak=PeakSettings(systematic_sigma_um=1.5))
    tracker = FocusTracker.create(estimator, scope_slide("kf-2d-lean", 1.5), noisy)
    documents: list[tuple[str, dict[str, Any]]] = []
    RE = RunEngine({})
    RE.subscribe(lambda name, document: documents.append((name, document)))
    scan(RE, scope, tracker)

    events = events_by_stream(documents)
    primary, planes = events["primary"], events[PLANES_STREAM]
    tiles = {(tile.row, tile.col): tile for tile in tracker.tiles}
    with_planes = [tile for tile in tiles.values() if tile.planes_um]
    assert with_planes, [tile.sigma_um for tile in tiles.values()]
    assert len(primary) == grid.n_tiles  # still one primary event per tile
    for data in primary:
        tile = tiles[data["focustrack_row"], data["focustrack_col"]]
        assert data["focustrack_planes"] == len(tile.planes_um)
    read_at: dict[tuple[int, int], list[float]] = {}
    for data in planes:
        read_at.setdefault((data["focustrack_row"], data["focustrack_col"]), []).append(data["z"])
        assert np.asarray(data["camera"]).shape == scope.microscope.spec.shape
    assert read_at == {
        (tile.row, tile.col): pytest.approx(list(tile.planes_um)) for tile in with_planes
    }
    assert scope.n_frames == tracker.n_frames + len(planes) + len(primary)


def descriptors_by_stream(documents: list[tuple[str, dict[str, Any]]]) -> dict[str, dict]:
    """The descriptor document of every stream, by its name."""
    return {doc["name"]: doc for name, doc in documents if name == "descriptor"}


def columns(documents: list[tuple[str, dict[str, Any]]], stream: str) -> dict[str, np.ndarray]:
    """A stream's data by key, each (n_events, *shape) of its descriptor's numpy dtype, as a
    catalog (databroker, tiled) that trusts the descriptor reads it."""
    data_keys = descriptors_by_stream(documents)[stream]["data_keys"]
    events = events_by_stream(documents)[stream]
    return {
        key: np.asarray([data[key] for data in events], dtype=np.dtype(data_key["dtype_numpy"]))
        for key, data_key in data_keys.items()
        if None not in data_key["shape"]  # ragged: no rectangular array
    }


@pytest.mark.slow  # the estimator's start, then 9 tiles and 115 frames: about 10 s
# databroker 1.x warns of its own v1 insert API (each document) and xarray's dims
@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning:databroker")
@pytest.mark.filterwarnings("ignore::FutureWarning:databroker")
@pytest.mark.filterwarnings("ignore::DeprecationWarning:intake")
def test_every_document_is_valid_and_says_units_dtypes_shapes_and_the_grid(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
) -> None:
    grid = small_scope.microscope.slides[small_scope.slide].grid
    tracker = FocusTracker.create(estimator, slide_of(small_scope, "kf-2d", 0.1))
    documents: list[tuple[str, dict[str, Any]]] = []
    RE = RunEngine({})
    RE.subscribe(lambda name, document: documents.append((name, document)))
    catalog = databroker.temp()  # a real databroker catalog, in a temporary folder
    RE.subscribe(catalog.v1.insert)
    uid = scan(RE, small_scope, tracker)
    # What a document store keeps (JSON, as databroker's and tiled's backends do): from
    # there on, only the descriptors tell each column's dtype and shape.
    stored = [(name, json.loads(json.dumps(doc, cls=NumpyEncoder))) for name, doc in documents]

    for name, document in documents + stored:  # event-model's schema of each kind of document
        schema_validators[DocumentNames(name)].validate(document)
    descriptors = descriptors_by_stream(documents)
    assert set(descriptors) == {"primary", STACK_STREAM, MAP_STREAM}
    events = events_by_stream(documents)
    for stream, descriptor in descriptors.items():
        for key, data_key in descriptor["data_keys"].items():
            assert "units" in data_key and "dtype_numpy" in data_key, (stream, key)
            dtype = np.dtype(data_key["dtype_numpy"])
            for data in events[stream]:  # each value as the descriptor says
                value = np.asarray(data[key])
                assert value.ndim == len(data_key["shape"]), (stream, key)
                assert all(
                    side is None or side == length
                    for side, length in zip(data_key["shape"], value.shape, strict=True)
                ), (stream, key, value.shape)
                castable = np.can_cast(value.dtype, dtype, "same_kind")
                assert value.size == 0 or castable, (stream, key)  # [] is float64 to numpy
    primary_keys = descriptors["primary"]["data_keys"]
    for key in ("x", "y", "z", "focustrack_z_um", "focustrack_sigma_um"):
        assert primary_keys[key]["units"] == "um"
        assert primary_keys[key]["dtype"] == "number"
    assert primary_keys["camera"]["shape"] == list(small_scope.microscope.spec.shape)
    assert primary_keys["camera"]["dtype_numpy"] == "<u2"
    assert primary_keys["focustrack_flags"]["dtype"] == "array"
    assert primary_keys["focustrack_flags"]["shape"] == [None]
    flags = {flag.value for flag in FocusFlag}
    for data in events["primary"]:
        assert isinstance(data["focustrack_flags"], list)
        assert set(data["focustrack_flags"]) <= flags

    # The start document describes the grid as bluesky's grid_scan: y (rows, the slow
    # motor) then x, each from row or column 0, so a viewer draws row 0 at the top as the
    # OME-Zarr mosaic does: y falls with the row (lab_sim's stage, y up).
    start = stored[0][1]
    primary = columns(stored, "primary")
    assert primary["camera"].dtype == np.uint16
    np.testing.assert_array_equal(primary["camera"], [data["camera"] for data in events["primary"]])
    first, last_row, last_col = 0, grid.n_tiles - 1, grid.cols - 1  # serpentine order
    assert start["motors"] == ["y", "x"]
    assert start["shape"] == [grid.rows, grid.cols]
    assert start["num_points"] == grid.n_tiles
    assert start["snaking"] == [False, True]
    assert start["extents"] == [
        pytest.approx([primary["y"][first], primary["y"][last_row]]),
        pytest.approx([primary["x"][first], primary["x"][last_col]]),
    ]
    assert start["extents"][0][0] > start["extents"][0][1]
    assert start["hints"]["gridding"] == "rectilinear"
    assert [list(dimension) for dimension in start["hints"]["dimensions"]] == [
        [["y"], "primary"],
        [["x"], "primary"],
    ]

    # focus_stack: every frame names its tile, the run's stack number and its place in it.
    stacks = columns(stored, STACK_STREAM)
    assert primary_keys["focustrack_row"]["dtype_numpy"] == "<i8"
    tiles = list(
        dict.fromkeys(zip(stacks["focustrack_row"], stacks["focustrack_col"], strict=True))
    )
    assert tiles == [(tile.row, tile.col) for tile in grid.serpentine]
    stack, frame = stacks["focustrack_stack"], stacks["focustrack_stack_frame"]
    starts = np.flatnonzero(frame == 0)
    assert stack[0] == 0 and set(np.diff(stack)) <= {0, 1}
    assert np.array_equal(stack[starts], np.arange(len(starts)))  # a new stack at frame 0
    sequence = stacks["focustrack_sequence"]  # the estimator's, one per acquisition
    for begin, end in zip(starts, [*starts[1:], len(frame)], strict=True):
        assert np.array_equal(frame[begin:end], np.arange(end - begin))
        assert set(stack[begin:end]) == {stack[begin]}
        assert set(sequence[begin:end]) == {sequence[begin]}
    assert np.all(np.diff(sequence[starts]) > 0) and sequence[0] >= 0
    assert sequence[starts[-1]] == tracker.stack_sequence
    assert len(frame) == tracker.n_frames

    # focustrack_map: the estimator's final maps, (rows, cols), row 0 first.
    (in_memory,) = events[MAP_STREAM]  # nested lists, which tiled's writer (pyarrow) takes
    assert all(isinstance(in_memory[f"focustrack_{layer}"], list) for layer in MAP_LAYERS)
    focus_map = {key: column[0] for key, column in columns(stored, MAP_STREAM).items()}
    map_keys = descriptors[MAP_STREAM]["data_keys"]
    estimated = estimator.focus_map(tracker.slide_id)
    for layer in MAP_LAYERS:
        key = f"focustrack_{layer}"
        assert map_keys[key]["shape"] == [grid.rows, grid.cols]
        assert map_keys[key]["dims"] == ["row", "col"]
        assert map_keys[key]["units"] == "um"
        expected = np.array(getattr(estimated, layer), dtype=np.float64)
        np.testing.assert_array_equal(focus_map[key], expected)
    assert np.isfinite(focus_map["focustrack_smoothed_um"]).all()  # kf-2d smooths every tile

    # The same run read back from the catalog by key (databroker's v2 API, xarray). The
    # flags are ragged (a list per tile), which its reader cannot stack into one array:
    # they are left out, as a viewer of the heights would.
    run = catalog.v2[uid]
    read_primary = run.primary(exclude=["focustrack_flags"]).read()
    np.testing.assert_allclose(read_primary["focustrack_z_um"].values, primary["focustrack_z_um"])
    np.testing.assert_array_equal(read_primary["camera"].values, primary["camera"])
    assert run.primary.metadata["descriptors"][0]["data_keys"]["focustrack_z_um"]["units"] == "um"
    read_map = run[MAP_STREAM].read()
    np.testing.assert_array_equal(
        read_map["focustrack_posterior_um"].values[0], focus_map["focustrack_posterior_um"]
    )
    read_stacks = run[STACK_STREAM].read()
    np.testing.assert_array_equal(
        read_stacks["focustrack_stack"].values, stacks["focustrack_stack"]
    )
    assert run.metadata["start"]["motors"] == ["y", "x"]
    posterior_um = focus_map["focustrack_posterior_um"]
    for row, col, z_um in zip(
        primary["focustrack_row"],
        primary["focustrack_col"],
        primary["focustrack_z_um"],
        strict=True,
    ):
        assert posterior_um[row, col] == pytest.approx(z_um)


@pytest.mark.slow  # the estimator's start, then 9 tiles and 115 frames: about 10 s
def test_bluesky_s_own_viewer_draws_the_grid_with_row_0_at_the_top_as_the_mosaic(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    grid = small_scope.microscope.slides[small_scope.slide].grid
    tracker = FocusTracker.create(estimator, slide_of(small_scope, "kf-2d", 0.1))
    documents: list[tuple[str, dict[str, Any]]] = []
    RE = RunEngine({})
    RE.subscribe(lambda name, document: documents.append((name, document)))
    scan(RE, small_scope, tracker)
    # The run's primary stream through the viewer, which lays it out from the start
    # document's grid hints (a LiveGrid per key). Its figures are checked, not rendered:
    # it redraws on every event, seconds each; the other streams it would plot against
    # time are left out.
    monkeypatch.setattr(FigureCanvasAgg, "draw_idle", lambda *args, **kwargs: None)
    primary_uid = descriptors_by_stream(documents)["primary"]["uid"]
    viewer = BestEffortCallback()
    viewer.disable_table()
    plt.close("all")
    for name, document in documents:
        if name in ("start", "stop") or primary_uid in (
            document["uid"],
            document.get("descriptor"),
        ):
            viewer(name, document)

    # Each LiveGrid image of the primary stream, by the key its colour bar names.
    images = {
        image.colorbar.ax.get_ylabel(): image
        for number in plt.get_fignums()
        for axes in plt.figure(number).axes
        for image in axes.images
        if image.colorbar is not None
    }
    rows, cols = np.indices((grid.rows, grid.cols))
    # Every tile in its place, the serpentine rows unfolded (the start's snaking).
    np.testing.assert_array_equal(images["focustrack_row"].get_array(), rows)
    np.testing.assert_array_equal(images["focustrack_col"].get_array(), cols)
    # Row 0 (the image's first row, drawn at `bottom` with origin "lower") at the top of
    # axes whose y grows upwards, as in the OME-Zarr mosaic.
    image = images["focustrack_row"]
    _, _, first_row_y, last_row_y = image.get_extent()
    low_y, high_y = image.axes.get_ylim()
    assert first_row_y > last_row_y and low_y < high_y
    plt.close("all")


def test_a_plan_run_again_after_an_abort_picks_up_where_it_stopped(
    estimator: EstimatorClient,
    scope: SimScope,
    scope_slide: Callable[[str, float], SlideCreate],
) -> None:
    """A run aborted mid-scan (a camera failing) and the plan run again: it moved to tile
    (0, 0) and stopped at a TileOrderError; it goes on from the tile the estimator expects,
    the one cut short resumed by the tracker, and the slide is finished."""
    grid = scope.microscope.slides[scope.slide].grid
    tracker = FocusTracker.create(estimator, scope_slide("kf-2d", 0.1))
    frame = scope.frame

    def failing_frame() -> np.ndarray:
        if scope.n_frames >= 60:
            raise RuntimeError("the camera lost its connection")
        return frame()

    scope.frame = failing_frame  # type: ignore[method-assign]
    documents: list[tuple[str, dict[str, Any]]] = []
    RE = RunEngine({})
    RE.subscribe(lambda name, document: documents.append((name, document)))
    with pytest.raises(RuntimeError, match="lost its connection"):
        scan(RE, scope, tracker)
    tiles_before = {(t.row, t.col) for t in tracker.tiles}
    assert 0 < len(tiles_before) < grid.n_tiles
    scope.frame = frame  # type: ignore[method-assign]
    documents.clear()
    scan(RE, scope, tracker)
    assert documents[-1][1]["exit_status"] == "success"
    primary = events_by_stream(documents)["primary"]
    again = [(data["focustrack_row"], data["focustrack_col"]) for data in primary]
    assert not tiles_before & set(again)  # no finished tile is scanned twice
    assert len(again) == grid.n_tiles - len(tiles_before)
    assert estimator.next(tracker.slide_id).done
