"""FocusTrack as a pymmcore-plus MDA engine: each grid position's z-range and best z.

    engine = FocusTrackEngine(core, estimator, strategy="kf-2d")
    core.mda.set_engine(engine)
    core.mda.run(useq.MDASequence(grid_plan=useq.GridRowsColumns(rows=6, columns=6)))

On the first event of every grid position, the engine (a `MDAEngine`) asks the
estimator for the position's z-range, snaps the stack through the core's focus
stage and camera, measures its focus locally, posts the measurement (and takes
the stacks the estimator asks for again), then moves the focus stage to the best
z; the event's own image, the one the MDA keeps, is snapped there. The stacks are
not MDA frames: only the kept images reach the MDA's writers and `frameReady`.

Where one image of a position is too unsure to be in focus (a slide with a stated
risk, as strategy kf-2d-lean keeps: `TileFocus.planes_um`), the engine snaps each of
the position's planes and the MDA frame is their fusion (extended depth of field,
`focustrack_core.fusion`): one frame per position still, so every writer takes it,
and the event's metadata lists the planes (`focustrack_planes_um`). A lab loop that
wants the planes themselves as separate images drives `FocusTracker` itself and snaps
them at `TileFocus.planes_um`.

The grid's rows and columns are FocusTrack's tiles (row, col); the MDA must visit
them in the estimator's serpentine order, which is useq's default `row_wise_snake`.
The estimator's slide is the grid as the stage moves: its pitch is the distance
between neighbouring positions (the field of view less the overlap), its origin
the stage position of tile (0, 0) (a relative grid is offset by the sequence's one
stage position). The estimator's y grows with the row where useq's stage y shrinks:
distances, all its model uses, are the same.

A relative z plan (`ZRangeAround`, `ZAboveBelow`, `ZRelativePositions`) is the
lab's own z-stack around each position's focus: its heights are offsets from
FocusTrack's z for the position, and each is an MDA frame (no fusion of planes
then). An absolute z plan is refused: FocusTrack chooses where the focus is.

Every event of a focused position carries FocusTrack's result in its metadata
(`focustrack_z_um`, `focustrack_sigma_um`, `focustrack_flags`: the flags of its
last measured stack, empty where a focus was found). A position whose focus
cannot be found (a flat stack: nothing in view, or a device whose images do not
change with z) is imaged at the estimator's prediction once the estimator gives it
up (a flat curve gets one widest stack more, then the next position); at the end of
the sequence the engine logs a warning naming such positions, and `engine.summary`
(`tracker.ScanSummary`) says so.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from pymmcore_plus import CMMCorePlus
from pymmcore_plus.mda import MDAEngine
from pymmcore_plus.metadata import FrameMetaV1
from useq import (
    GridFromEdges,
    GridRowsColumns,
    GridWidthHeight,
    MDAEvent,
    MDASequence,
    OrderMode,
    Position,
)

from focustrack_client import EstimatorClient
from focustrack_client.models import Grid, SlideCreate
from focustrack_core.fusion import fuse_planes
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.tracker import FocusTracker, ScanSummary, TileFocus

log = logging.getLogger(__name__)

#: What an MDA engine yields per image (pymmcore-plus's `PImagePayload`, typing only there).
ImagePayload = tuple[np.ndarray, MDAEvent, FrameMetaV1]
#: The grid plans FocusTrack scans: rectangular, rows and columns.
RectangularGrid = GridRowsColumns | GridFromEdges | GridWidthHeight
#: Relative tolerance on the grid's row and column steps being equal (the estimator's one pitch).
PITCH_RTOL = 1e-6


class FocusTrackEngine(MDAEngine):
    """An MDA engine that focuses each grid position with FocusTrack (module docstring).

    `slide` holds the estimator slide's settings other than its grid (strategy,
    start_z_um, start_sigma_um, dof_um, noise_sigma_um, z_range, params), as
    `focustrack_client.models.SlideCreate` names them.
    """

    def __init__(
        self,
        mmcore: CMMCorePlus,
        estimator: EstimatorClient,
        *,
        focus: FocusSettings | None = None,
        **slide: Any,
    ) -> None:
        # Hardware sequencing hands a z-stack's heights to the stage before it runs; a
        # position's heights are known only once FocusTrack has focused it.
        super().__init__(mmcore, use_hardware_sequencing=False)
        self.estimator = estimator
        self.focus_settings = focus
        self.slide = slide
        self.tracker: FocusTracker | None = None
        #: The last sequence's outcome, once it has ended (None before).
        self.summary: ScanSummary | None = None
        self._tiles: dict[int, tuple[int, int]] = {}  # grid index "g" -> (row, col)
        self._focused: dict[int, TileFocus] = {}  # grid index "g" -> its focus
        self._base_z_um = 0.0  # what the events' z is relative to: the stage position's z
        self._z_stack = False  # the sequence has a (relative) z plan: the lab's own z-stack
        # The (row, col) whose stack `_snap_stack` takes, to name it where the stage fails.
        self._snapping: tuple[int, int] | None = None

    def setup_sequence(self, sequence: MDASequence) -> Any:
        summary = super().setup_sequence(sequence)  # sets the grid's field of view
        grid = sequence.grid_plan
        if not isinstance(grid, RectangularGrid):
            raise ValueError(
                "FocusTrackEngine needs a sequence with a rectangular grid_plan "
                f"(GridRowsColumns, GridFromEdges or GridWidthHeight), not {type(grid).__name__}"
            )
        z_plan = sequence.z_plan
        if z_plan is not None and not z_plan.is_relative:
            raise ValueError(
                f"FocusTrackEngine chooses each position's z: an absolute z plan "
                f"({type(z_plan).__name__}) cannot follow it; give a relative one "
                "(ZRangeAround, ZAboveBelow, ZRelativePositions) for a z-stack around the focus"
            )
        if OrderMode(grid.mode) is not OrderMode.row_wise_snake:
            raise ValueError(
                f"the grid is visited {grid.mode}; FocusTrack's estimator predicts along "
                "row_wise_snake (row 0 left to right, row 1 right to left, ...)"
            )
        if len(sequence.stage_positions) > 1:
            raise ValueError(
                f"FocusTrackEngine scans one grid: give at most one stage position (the "
                f"grid's centre), not {len(sequence.stage_positions)}"
            )
        position = sequence.stage_positions[0] if sequence.stage_positions else None
        scan_grid, self._tiles = _scan_grid(grid, position)
        self._focused = {}
        self._base_z_um = position.z if position is not None and position.z is not None else 0.0
        self._z_stack = z_plan is not None
        self.summary = None
        self.tracker = FocusTracker.create(
            self.estimator,
            SlideCreate(grid=scan_grid, **self.slide),
            self.focus_settings,
        )
        return summary

    def setup_single_event(self, event: MDAEvent) -> None:
        super().setup_single_event(event)  # moves to the position (x, y)
        index = event.index.get("g")
        if index is None or self.tracker is None:
            return
        if index not in self._focused:
            row, col = self._tiles[index]
            self._snapping = (row, col)
            self._focused[index] = self.tracker.focus(row, col, self._snap_stack)
        self.mmcore.setZPosition(self._focused[index].z_um + self._z_offset_um(event))
        self.mmcore.waitForDevice(self.mmcore.getFocusDevice())

    def exec_single_event(self, event: MDAEvent) -> Iterator[ImagePayload | None]:
        """The event's image, its metadata carrying the position's focus: snapped at the
        position's best z (plus the z plan's offset), or the fusion of its planes where it
        has some and the sequence no z plan (module docstring)."""
        index = event.index.get("g")
        focus = None if index is None else self._focused.get(index)
        if focus is None:
            yield from super().exec_single_event(event)
            return
        event = event.model_copy(update={"metadata": {**event.metadata, **_metadata(focus)}})
        if self._z_stack or not focus.planes_um:
            yield from super().exec_single_event(event)
            return
        self._snapping = (focus.row, focus.col)
        planes = self._snap_stack(np.asarray(focus.planes_um))
        runner_t0 = event.metadata.get("runner_t0") or time.perf_counter()  # as the base's
        self.mmcore.setZPosition(focus.z_um)  # where the next event of this position starts
        self.mmcore.waitForDevice(self.mmcore.getFocusDevice())
        event = event.model_copy(
            update={"metadata": {**event.metadata, "focustrack_planes_um": list(focus.planes_um)}}
        )
        meta: FrameMetaV1 = self.get_frame_metadata(
            event,
            runner_time_ms=1e3 * (time.perf_counter() - runner_t0),
            camera_device=self.mmcore.getCameraDevice(),
        )
        yield fuse_planes(planes), event, meta

    def teardown_sequence(self, sequence: MDASequence) -> None:
        """Ends the sequence as the base engine does; keeps its `summary`, and warns when a
        position was imaged without a measured focus."""
        super().teardown_sequence(sequence)
        if self.tracker is None:
            return
        self.summary = self.tracker.summary()
        if self.summary.unfocused:
            log.warning("FocusTrack: %s", self.summary)

    def _z_offset_um(self, event: MDAEvent) -> float:
        """The event's z relative to its position's (its z plan's offset and its channel's),
        um; 0 for an event without a z."""
        return 0.0 if event.z_pos is None else event.z_pos - self._base_z_um

    def _snap_stack(self, z_um: np.ndarray) -> np.ndarray:
        """Frames (n, H, W[, C]) snapped at z_um (n,) with the core's focus stage and camera.

        A move the focus stage refuses (Micro-Manager's RuntimeError, "Position out of
        range" past its travel) is raised again naming the tile, the z and the stack: the
        core's message alone says none of them.
        """
        core = self.mmcore
        frames = []
        for z in z_um:
            try:
                core.setZPosition(float(z))
                core.waitForDevice(core.getFocusDevice())
            except RuntimeError as error:
                tile = "" if self._snapping is None else f" at tile {self._snapping}"
                raise RuntimeError(
                    f"the focus stage could not move to z = {float(z):g} um{tile}, a frame of "
                    f"a {len(z_um)}-frame stack from {float(np.min(z_um)):g} to "
                    f"{float(np.max(z_um)):g} um: {error}. Check the stage's travel limits "
                    "against the slide's start_z_um and start_sigma_um (the first stacks span "
                    "z_range.k_sigma start sigmas either side of start_z_um)"
                ) from error
            core.snapImage()
            frames.append(core.getImage())
        return np.stack(frames)


def _metadata(focus: TileFocus) -> dict[str, Any]:
    """What an MDA event of a focused position says of its focus (module docstring)."""
    return {
        "focustrack_z_um": focus.z_um,
        "focustrack_sigma_um": focus.sigma_um,
        "focustrack_flags": sorted(str(flag) for flag in focus.flags),
    }


def _scan_grid(
    grid: RectangularGrid, position: Position | None
) -> tuple[Grid, dict[int, tuple[int, int]]]:
    """The estimator's grid of the stage positions that `grid` visits, and the (row, col)
    of each grid index; ValueError where its row and column steps differ (the estimator's
    grid has one pitch).

    Positions as useq gives them to the MDA: a relative grid offset by `position`'s
    (x, y), an absolute one as it is.
    """
    offset_x_um = (position.x or 0.0) if position is not None and grid.is_relative else 0.0
    offset_y_um = (position.y or 0.0) if position is not None and grid.is_relative else 0.0
    tiles: dict[int, tuple[int, int]] = {}
    xy_um: dict[tuple[int, int], tuple[float, float]] = {}
    for index, point in enumerate(grid.iter_grid_positions()):
        tile = (point.grid_row or 0, point.grid_col or 0)
        tiles[index] = tile
        xy_um[tile] = ((point.x or 0.0) + offset_x_um, (point.y or 0.0) + offset_y_um)
    rows = 1 + max(row for row, _ in tiles.values())
    cols = 1 + max(col for _, col in tiles.values())
    x0_um, y0_um = xy_um[0, 0]
    steps_um = [abs(xy_um[0, 1][0] - x0_um)] if cols > 1 else []
    steps_um += [abs(xy_um[1, 0][1] - y0_um)] if rows > 1 else []
    if len(steps_um) == 2 and not math.isclose(*steps_um, rel_tol=PITCH_RTOL):
        raise ValueError(
            f"the grid steps {steps_um[0]:g} um between columns and {steps_um[1]:g} um "
            "between rows; FocusTrack's estimator takes one pitch: make the field of view "
            "and overlap give equal steps (e.g. fov_width == fov_height)"
        )
    pitch_um = steps_um[0] if steps_um else (grid.fov_width or 1.0)
    return Grid(
        rows=rows, cols=cols, pitch_um=pitch_um, origin_x_um=x0_um, origin_y_um=y0_um
    ), tiles
