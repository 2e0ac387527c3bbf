"""The simulated microscope as lab devices: try FocusTrack's integrations without hardware.

Both are backed by `focustrack_instrument_sim.microscope.Microscope` through a
`SimScope`, whose camera renders the tile under the objective at the focus z:
- `simulated_core(scope)`: a pymmcore-plus `UniMMCore` with the lab's three
  pure-Python devices (`focustrack_core.mm_devices.scope_core`), a camera ("Camera"), an
  XY stage ("XY") and a focus stage ("Z"); no Micro-Manager installation is needed;
- `simulated_ophyd(scope)`: ophyd's simulated motors x, y, z (`ophyd.sim.SynAxis`,
  in um) and a camera (`ophyd.sim.SynSignal`) that images where they stand, each
  describing its data keys as a real device does (units, numpy dtype, shape).

Stage coordinates are those of a useq grid centred on (0, 0): x grows with the
column, y shrinks with the row (useq's `GridRowsColumns` puts row 0 at the top),
`pitch_um` apart, so grid position (row, col) images the simulator's tile (row, col).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from ophyd.sim import SynAxis, SynSignal
from pymmcore_plus.experimental.unicore import UniMMCore

from focustrack_core.mm_devices import scope_core
from focustrack_instrument_sim.microscope import Microscope
from focustrack_lab.bluesky import UM, with_data_key

#: Which colour channel the monochrome camera sees (green: the sharpest PSF of the three).
GREEN = 1


@dataclass
class SimScope:
    """The simulated microscope and where its stages are (um); counts the frames snapped."""

    microscope: Microscope
    slide: str
    x_um: float = 0.0
    y_um: float = 0.0
    z_um: float = 0.0
    exposure_ms: float = 10.0
    n_frames: int = 0

    @property
    def shape(self) -> tuple[int, int]:
        """The camera's frame, (height, width) px."""
        return self.microscope.spec.shape

    def tile(self) -> tuple[int, int]:
        """The (row, col) of the tile under the objective (see the module docstring)."""
        grid = self.microscope.slides[self.slide].grid
        col = round(self.x_um / grid.pitch_um + (grid.cols - 1) / 2)
        row = round((grid.rows - 1) / 2 - self.y_um / grid.pitch_um)
        return row, col

    def frame(self) -> np.ndarray:
        """The camera frame (height, width) uint16 at the stages' position."""
        row, col = self.tile()
        stack = self.microscope.acquire(
            self.slide, row, col, self.z_um, 1.0, 1, self.exposure_ms / 1000.0
        )
        self.n_frames += 1
        return stack.pixels[0, ..., GREEN]

    def truth_um(self) -> np.ndarray:
        """The true focus of every tile, (rows, cols) in um (evaluation only)."""
        return self.microscope.truth_um(self.slide)[0]


def simulated_core(scope: SimScope) -> UniMMCore:
    """A UniMMCore whose camera, XY stage and focus stage are `scope`'s."""
    return scope_core(scope)


class UmAxis(SynAxis):
    """ophyd's simulated motor, whose readback and setpoint say um and float64: SynAxis
    reports neither units nor, before its first move, a float (it starts at integer 0)."""

    def describe(self) -> dict[str, dict[str, Any]]:
        return with_data_key(super().describe(), UM, np.dtype(np.float64))


class SimCameraSignal(SynSignal):
    """ophyd's simulated detector as the scope's camera: each reading one frame
    (height, width) uint16 in counts (the camera's digital numbers)."""

    def __init__(self, scope: SimScope, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.frame_shape = scope.microscope.spec.shape

    def describe(self) -> dict[str, dict[str, Any]]:
        return with_data_key(
            super().describe(), "counts", np.dtype(np.uint16), self.frame_shape, ("y", "x")
        )


def simulated_ophyd(scope: SimScope) -> tuple[SynSignal, SynAxis, SynAxis, SynAxis]:
    """(camera, x, y, z): ophyd's simulated motors (um) and a camera imaging where they stand."""
    x, y, z = (UmAxis(name=name, egu=UM) for name in ("x", "y", "z"))

    def image() -> np.ndarray:
        scope.x_um, scope.y_um, scope.z_um = x.position, y.position, z.position
        return scope.frame()

    scope.n_frames -= 1  # SynSignal reads its function once when it is made
    camera = SimCameraSignal(scope, func=image, name="camera")
    return camera, x, y, z


def grid_placement(scope: SimScope) -> dict[str, Any]:
    """`focustrack_grid`'s grid keywords (rows, cols, pitch_um, x0_um, y0_um) for the
    scope's slide at these stage coordinates: tile (0, 0) top left, the grid centred on 0."""
    grid = scope.microscope.slides[scope.slide].grid
    return {
        "rows": grid.rows,
        "cols": grid.cols,
        "pitch_um": grid.pitch_um,
        "x0_um": -(grid.cols - 1) / 2 * grid.pitch_um,
        "y0_um": (grid.rows - 1) / 2 * grid.pitch_um,
    }
