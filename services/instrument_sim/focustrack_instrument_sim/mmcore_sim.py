"""The simulator behind Micro-Manager's device layer (`--backend mmcore-sim`).

A pymmcore-plus `UniMMCore` whose camera, focus stage and XY stage are pure-Python devices
over the simulated microscope (`microscope.Microscope`), served by the MMCore backend
(`mmcore_backend.MMCoreInstrument`) exactly as a real microscope's core would be: every
stack goes through MMCore's calls (moves, waits, snaps, images), none through the
simulator's own stack path. Scanning one slide with `--backend sim` and with
`--backend mmcore-sim` (same seed and slide options) shows what the device path changes:
nothing in the frames, so the same focus, frames per tile and accuracy (`focustrack bench
mmcore`).

The camera is monochrome: it gives the simulator's green channel, the one the focus
service reads in a colour frame. The slide's tile (row, col) is at the simulator's stage
position (`ScanGrid.stage_xy_um`), so the XY stage's position says which tile is under the
objective. One slide (`--slides 1`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from pymmcore_plus.experimental.unicore import (
    SimpleCameraDevice,
    StageDevice,
    UniMMCore,
    XYStageDevice,
)

from focustrack_core.geometry import ScanGrid
from focustrack_instrument_sim.instrument import AcquisitionRefusedError, FocusTruth
from focustrack_instrument_sim.microscope import Microscope
from focustrack_instrument_sim.mmcore_backend import MMCoreInstrument, release_core
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
from focustrack_instrument_sim.simulated import SimulatedInstrument

#: The colour channel the monochrome camera gives (green: the focus service's channel).
GREEN = 1


class Position:
    """Where the simulated stages stand (um) and the camera's exposure (ms): the state the
    three devices share, as a real microscope's stand is shared by its devices."""

    def __init__(self, exposure_ms: float) -> None:
        self.x_um = self.y_um = self.z_um = 0.0
        self.exposure_ms = exposure_ms


class SimulatedCamera(SimpleCameraDevice):
    """The tile of `slide` under the objective, at the focus stage's z: (height, width)
    uint16 counts, the simulator's green channel."""

    def __init__(self, microscope: Microscope, slide: str, position: Position) -> None:
        super().__init__()
        self.microscope, self.slide, self.position = microscope, slide, position
        self.grid: ScanGrid = microscope.slides[slide].grid

    def sensor_shape(self) -> tuple[int, int]:
        return self.microscope.spec.shape

    def dtype(self) -> np.dtype:
        return np.dtype(np.uint16)

    def get_exposure(self) -> float:
        return self.position.exposure_ms

    def set_exposure(self, exposure: float) -> None:
        self.position.exposure_ms = exposure

    def snap(self, buffer: np.ndarray) -> Mapping[str, object]:
        position, grid = self.position, self.grid
        # The tile whose centre is nearest. The simulator's refusal (a stage off the slide,
        # a focus out of range) is raised as a C++ camera's failure reaches pymmcore: a
        # RuntimeError, which the MMCore backend reports as the camera's DeviceError.
        row = round((position.y_um - grid.origin_y_um) / grid.pitch_um)
        col = round((position.x_um - grid.origin_x_um) / grid.pitch_um)
        try:
            stack = self.microscope.acquire(
                self.slide, row, col, position.z_um, 1.0, 1, position.exposure_ms / 1000.0
            )
        except AcquisitionRefusedError as refusal:
            raise RuntimeError(f"nothing to image here: {refusal}") from refusal
        buffer[:] = stack.pixels[0, ..., GREEN]
        return {"z_um": position.z_um, "row": row, "col": col}


class SimulatedXYStage(XYStageDevice):
    """Moves at once (the simulator's stage times its own moves)."""

    def __init__(self, position: Position) -> None:
        super().__init__()
        self.position = position

    def set_position_um(self, x: float, y: float) -> None:
        self.position.x_um, self.position.y_um = x, y

    def get_position_um(self) -> tuple[float, float]:
        return self.position.x_um, self.position.y_um

    def set_origin_x(self) -> None:
        self.position.x_um = 0.0

    def set_origin_y(self) -> None:
        self.position.y_um = 0.0

    def home(self) -> None:
        self.set_position_um(0.0, 0.0)

    def stop(self) -> None:
        """Moves are instantaneous: nothing to stop."""


class SimulatedFocusStage(StageDevice):
    """Moves at once."""

    def __init__(self, position: Position) -> None:
        super().__init__()
        self.position = position

    def set_position_um(self, val: float) -> None:
        self.position.z_um = val

    def get_position_um(self) -> float:
        return self.position.z_um

    def set_origin(self) -> None:
        self.position.z_um = 0.0

    def home(self) -> None:
        self.position.z_um = 0.0

    def stop(self) -> None:
        """Moves are instantaneous: nothing to stop."""


def simulated_core(microscope: Microscope, slide: str) -> UniMMCore:
    """A UniMMCore whose camera ("Camera"), XY stage ("XY") and focus stage ("Z") image
    `slide` of `microscope`."""
    position = Position(1000.0 * microscope.spec.stage.timing.exposure_s)
    core = UniMMCore()
    try:
        for label, device in (
            ("Camera", SimulatedCamera(microscope, slide, position)),
            ("XY", SimulatedXYStage(position)),
            ("Z", SimulatedFocusStage(position)),
        ):
            core.loadPyDevice(label, device)
            core.initializeDevice(label)
        core.setCameraDevice("Camera")
        core.setXYStageDevice("XY")
        core.setFocusDevice("Z")
        core.setAutoShutter(False)  # there is no shutter to open and close
    except BaseException:
        release_core(core)
        raise
    return core


class SimulatedMMCoreInstrument(MMCoreInstrument):
    """The MMCore backend over `simulated_core(microscope, slide)`, with the simulator's
    grid, focus range and optics as its options (`options` gives the rest: timeouts,
    tolerances), and the simulator's truth (a `TruthSource`)."""

    def __init__(self, microscope: Microscope, options: MMCoreOptions | None = None) -> None:
        if len(microscope.slides) != 1:
            raise ValueError(
                f"--backend mmcore-sim images one slide, not {len(microscope.slides)}: "
                "give --slides 1"
            )
        self.simulator = SimulatedInstrument(microscope)
        slide = self.simulator.describe().slides[0]
        spec = microscope.spec
        z_low_um, z_high_um = spec.stage.z_range_um
        options = (options or MMCoreOptions()).model_copy(
            update={
                "mm_rows": slide.grid.rows,
                "mm_cols": slide.grid.cols,
                "mm_pitch_um": slide.grid.pitch_um,
                "mm_origin_x_um": slide.grid.origin_x_um,
                "mm_origin_y_um": slide.grid.origin_y_um,
                "mm_slides": 1,
                "mm_z_min_um": z_low_um,
                "mm_z_max_um": z_high_um,
                "mm_max_frames": spec.max_frames,
                "mm_pixel_size_um": spec.optics.pixel_size_um,
                "mm_na": spec.optics.numerical_aperture,
                "mm_magnification": spec.optics.magnification,
                "mm_wavelength_um": spec.optics.reference_wavelength_um,
                "mm_refractive_index": spec.optics.refractive_index,
            }
        )
        super().__init__(simulated_core(microscope, slide.name), options)

    def truth(self, slide: str) -> FocusTruth:
        return self.simulator.truth(slide)

    def close(self) -> None:
        super().close()
        self.simulator.close()
