"""The Bluesky plan with an ophyd Device camera, whose image is not keyed by its name."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from bluesky import RunEngine
from ophyd import Component, Device, Signal
from ophyd.status import StatusBase

from focustrack.lab_sim import SimScope, grid_placement, simulated_ophyd
from focustrack_client import EstimatorClient
from focustrack_client.models import SlideCreate
from focustrack_lab.bluesky import focustrack_grid
from focustrack_lab.tracker import FocusTracker


class AreaCamera(Device):
    """As an area detector: the image is one reading among others (`cam_image`, and a
    scalar `cam_acquire_time`), none keyed `cam`."""

    image = Component(Signal, value=np.zeros((64, 64), dtype=np.uint16), kind="normal")
    acquire_time = Component(Signal, value=0.05, kind="normal")

    def __init__(self, *args: Any, snap: Callable[[], np.ndarray], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.snap = snap

    def trigger(self) -> StatusBase:
        self.image.put(self.snap())
        status = StatusBase()
        status.set_finished()
        return status


class TwoImageCamera(AreaCamera):
    """Two readings of 2 dimensions and none keyed by its name: which is the image?"""

    dark = Component(Signal, value=np.zeros((64, 64), dtype=np.uint16), kind="normal")


def plan(camera: Any, scope: SimScope, tracker: FocusTracker, x: Any, y: Any, z: Any) -> Any:
    return focustrack_grid(camera, x, y, z, tracker, **grid_placement(scope))


def test_a_device_camera_s_one_image_reading_is_taken_as_its_image(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
) -> None:
    """It raised a bare KeyError: 'cam' (the plan read `readings[camera.name]`)."""
    tracker = FocusTracker.create(estimator, slide_of(small_scope, "kf-2d", 0.1))
    _, x, y, z = simulated_ophyd(small_scope)

    def snap() -> np.ndarray:
        small_scope.x_um, small_scope.y_um = x.position, y.position
        small_scope.z_um = z.position
        return small_scope.frame()

    camera = AreaCamera(name="cam", snap=snap)
    RunEngine({})(plan(camera, small_scope, tracker, x, y, z))
    grid = small_scope.microscope.slides[small_scope.slide].grid
    assert len(tracker.tiles) == grid.rows * grid.cols
    # The frames focus was measured on are the camera's images (the slide has empty tiles).
    assert any(tile.last is not None and tile.last.best_z_um is not None for tile in tracker.tiles)
    assert small_scope.n_frames == tracker.n_frames + grid.rows * grid.cols


def test_a_camera_without_one_image_reading_is_refused_naming_its_keys_before_any_move(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
) -> None:
    tracker = FocusTracker.create(estimator, slide_of(small_scope, "kf-2d", 0.1))
    _, x, y, z = simulated_ophyd(small_scope)
    camera = TwoImageCamera(name="cam", snap=small_scope.frame)
    RE = RunEngine({})
    documents: list[str] = []
    RE.subscribe(lambda name, _: documents.append(name))
    with pytest.raises(ValueError, match=r"which reading of camera 'cam' is its image.*cam_dark"):
        RE(plan(camera, small_scope, tracker, x, y, z))
    assert documents == [] and small_scope.n_frames == 0
