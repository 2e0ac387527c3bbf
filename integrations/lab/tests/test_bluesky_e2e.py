"""The Bluesky plan on a real RunEngine with ophyd.sim motors, against a real estimator."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from bluesky import RunEngine
from bluesky.callbacks import LiveTable

from focustrack.lab_sim import SimScope, simulated_ophyd
from focustrack_client import EstimatorClient
from focustrack_client.models import SlideCreate
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.bluesky import PLANES_STREAM, STACK_STREAM, focustrack_grid
from focustrack_lab.tracker import FocusTracker


def scan(RE: RunEngine, scope: SimScope, tracker: FocusTracker) -> str:
    """Runs the plan over the scope's slide with ophyd.sim devices; the run's uid."""
    grid = scope.microscope.slides[scope.slide].grid
    camera, x, y, z = simulated_ophyd(scope)
    (run_uid,) = RE(
        focustrack_grid(
            camera,
            x,
            y,
            z,
            tracker,
            rows=grid.rows,
            cols=grid.cols,
            pitch_um=grid.pitch_um,
            # Tile (row, col) at the simulator's stage coordinates (lab_sim: centred on 0, y up).
            x0_um=-(grid.cols - 1) / 2 * grid.pitch_um,
            y0_um=(grid.rows - 1) / 2 * grid.pitch_um,
        )
    )
    return str(run_uid)


def events_by_stream(documents: list[tuple[str, dict[str, Any]]]) -> dict[str, list[dict]]:
    """The data of every event document, by the name of its stream."""
    streams = {doc["uid"]: doc["name"] for name, doc in documents if name == "descriptor"}
    events: dict[str, list[dict]] = {}
    for name, doc in documents:
        if name == "event":
            events.setdefault(streams[doc["descriptor"]], []).append(doc["data"])
    return events


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
