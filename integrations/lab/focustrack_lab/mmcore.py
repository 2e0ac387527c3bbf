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
FocusTrack chooses z: a sequence with a z plan is refused.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from pymmcore_plus import CMMCorePlus
from pymmcore_plus.mda import MDAEngine
from pymmcore_plus.metadata import FrameMetaV1
from useq import GridFromEdges, GridRowsColumns, GridWidthHeight, MDAEvent, MDASequence, OrderMode

from focustrack_client import EstimatorClient
from focustrack_client.models import Grid, SlideCreate
from focustrack_core.fusion import fuse_planes
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.tracker import FocusTracker, TileFocus

#: What an MDA engine yields per image (pymmcore-plus's `PImagePayload`, typing only there).
ImagePayload = tuple[np.ndarray, MDAEvent, FrameMetaV1]


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
        super().__init__(mmcore)
        self.estimator = estimator
        self.focus_settings = focus
        self.slide = slide
        self.tracker: FocusTracker | None = None
        self._tiles: dict[int, tuple[int, int]] = {}  # grid index "g" -> (row, col)
        self._focused: dict[int, TileFocus] = {}  # grid index "g" -> its focus

    def setup_sequence(self, sequence: MDASequence) -> Any:
        summary = super().setup_sequence(sequence)  # sets the grid's field of view
        grid = sequence.grid_plan
        if not isinstance(grid, GridRowsColumns | GridFromEdges | GridWidthHeight):
            raise ValueError(
                "FocusTrackEngine needs a sequence with a rectangular grid_plan "
                f"(GridRowsColumns, GridFromEdges or GridWidthHeight), not {type(grid).__name__}"
            )
        if sequence.z_plan is not None:
            raise ValueError("FocusTrackEngine chooses each position's z: drop the z_plan")
        if OrderMode(grid.mode) is not OrderMode.row_wise_snake:
            raise ValueError(
                f"the grid is visited {grid.mode}; FocusTrack's estimator predicts along "
                "row_wise_snake (row 0 left to right, row 1 right to left, ...)"
            )
        positions = list(grid.iter_grid_positions())
        self._tiles = {
            index: (position.grid_row or 0, position.grid_col or 0)
            for index, position in enumerate(positions)
        }
        self._focused = {}
        rows = 1 + max(row for row, _ in self._tiles.values())
        cols = 1 + max(col for _, col in self._tiles.values())
        pitch_um = grid.fov_width or 1.0
        self.tracker = FocusTracker.create(
            self.estimator,
            SlideCreate(grid=Grid(rows=rows, cols=cols, pitch_um=pitch_um), **self.slide),
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
            self._focused[index] = self.tracker.focus(row, col, self._snap_stack)
        self.mmcore.setZPosition(self._focused[index].z_um)
        self.mmcore.waitForDevice(self.mmcore.getFocusDevice())

    def exec_single_event(self, event: MDAEvent) -> Iterator[ImagePayload | None]:
        """The event's image: snapped at the position's best z, or the fusion of its
        planes where it has some (module docstring)."""
        index = event.index.get("g")
        focus = None if index is None else self._focused.get(index)
        if index is None or focus is None or not focus.planes_um:
            yield from super().exec_single_event(event)
            return
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

    def _snap_stack(self, z_um: np.ndarray) -> np.ndarray:
        """Frames (n, H, W[, C]) snapped at z_um (n,) with the core's focus stage and camera."""
        core = self.mmcore
        frames = []
        for z in z_um:
            core.setZPosition(float(z))
            core.waitForDevice(core.getFocusDevice())
            core.snapImage()
            frames.append(core.getImage())
        return np.stack(frames)
