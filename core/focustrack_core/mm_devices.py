"""Pure-Python Micro-Manager devices over any `Scope`: a pymmcore-plus `UniMMCore` whose
camera, XY stage and focus stage image where a scope's stages stand (extra `mmcore`).

Shared by the lab's synthetic microscope (`focustrack_lab.demo`) and the instrument
service's simulator behind Micro-Manager (`focustrack_instrument_sim.mmcore_sim`): each
brings its own `Scope` (its specimen and frame), these devices are the same. Stage
coordinates in um, exposure in ms, frames (height, width) uint16.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np
from pymmcore_plus.experimental.unicore import (
    SimpleCameraDevice,
    StageDevice,
    UniMMCore,
    XYStageDevice,
)


class Scope(Protocol):
    """What the devices of `scope_core` drive: stages (um), exposure (ms), the camera."""

    x_um: float
    y_um: float
    z_um: float
    exposure_ms: float

    @property
    def shape(self) -> tuple[int, int]:
        """The camera's frame, (height, width) px."""
        ...

    def frame(self) -> np.ndarray:
        """The camera frame (height, width) uint16 at the stages' position."""
        ...


class ScopeCamera(SimpleCameraDevice):
    """The camera: the scope's frame where its stages are."""

    def __init__(self, scope: Scope) -> None:
        super().__init__()
        self.scope = scope

    def sensor_shape(self) -> tuple[int, int]:
        return self.scope.shape

    def dtype(self) -> np.dtype:
        return np.dtype(np.uint16)

    def get_exposure(self) -> float:
        return self.scope.exposure_ms

    def set_exposure(self, exposure: float) -> None:
        self.scope.exposure_ms = exposure

    def snap(self, buffer: np.ndarray) -> Mapping[str, object]:
        buffer[:] = self.scope.frame()
        return {"z_um": self.scope.z_um}


class ScopeXYStage(XYStageDevice):
    """The XY stage: moves are instantaneous."""

    def __init__(self, scope: Scope) -> None:
        super().__init__()
        self.scope = scope

    def set_position_um(self, x: float, y: float) -> None:
        self.scope.x_um, self.scope.y_um = x, y

    def get_position_um(self) -> tuple[float, float]:
        return self.scope.x_um, self.scope.y_um

    def set_origin_x(self) -> None:
        self.scope.x_um = 0.0

    def set_origin_y(self) -> None:
        self.scope.y_um = 0.0

    def home(self) -> None:
        self.set_position_um(0.0, 0.0)

    def stop(self) -> None:
        """Moves are instantaneous: nothing to stop."""


class ScopeZStage(StageDevice):
    """The focus stage: moves are instantaneous."""

    def __init__(self, scope: Scope) -> None:
        super().__init__()
        self.scope = scope

    def set_position_um(self, val: float) -> None:
        self.scope.z_um = val

    def get_position_um(self) -> float:
        return self.scope.z_um

    def set_origin(self) -> None:
        self.scope.z_um = 0.0

    def home(self) -> None:
        self.scope.z_um = 0.0

    def stop(self) -> None:
        """Moves are instantaneous: nothing to stop."""


def scope_core(scope: Scope) -> UniMMCore:
    """A UniMMCore whose camera, XY stage and focus stage are `scope`'s."""
    core = UniMMCore()
    for label, device in (
        ("Camera", ScopeCamera(scope)),
        ("XY", ScopeXYStage(scope)),
        ("Z", ScopeZStage(scope)),
    ):
        core.loadPyDevice(label, device)
        core.initializeDevice(label)
    core.setCameraDevice("Camera")
    core.setXYStageDevice("XY")
    core.setFocusDevice("Z")
    core.setAutoShutter(False)  # there is no shutter to open and close
    return core
