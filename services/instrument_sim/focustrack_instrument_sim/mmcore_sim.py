"""The simulator behind Micro-Manager's device layer (`--backend mmcore-sim`).

A pymmcore-plus `UniMMCore` whose camera, focus stage and XY stage are pure-Python devices
(`focustrack_core.mm_devices`) over the simulated microscope (`microscope.Microscope`:
`SimulatedScope`), served by the MMCore backend
(`mmcore_backend.MMCoreInstrument`) exactly as a real microscope's core would be: every
stack goes through MMCore's calls (moves, waits, snaps, images), none through the
simulator's own stack path. Scanning one slide with `--backend sim` and with
`--backend mmcore-sim` (same seed and slide options) shows what the device path changes:
nothing in the frames, so the same focus, frames per tile and accuracy (`focustrack bench
mmcore`).

The camera is monochrome: it gives the simulator's green channel, the one the focus
service reads in a colour frame (a phase specimen's frames are monochrome already: every
channel holds the same counts). Its stack headers carry the simulator's imaging conditions
(wavelength, condenser and objective NA, gain, offset). The slide's tile (row, col) is at
the simulator's stage position (`ScanGrid.stage_xy_um`), so the XY stage's position says
which tile is under the objective. One slide (`--slides 1`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pymmcore_plus.experimental.unicore import UniMMCore

from focustrack_core.mm_devices import scope_core
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    FocusTruth,
    TilePhase,
)
from focustrack_instrument_sim.microscope import Microscope
from focustrack_instrument_sim.mmcore_backend import MMCoreInstrument
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
from focustrack_instrument_sim.simulated import SimulatedInstrument

#: The colour channel the monochrome camera gives (green: the focus service's channel).
GREEN = 1


@dataclass
class SimulatedScope:
    """`slide` of the simulated microscope as a `focustrack_core.mm_devices.Scope`: where
    the stages stand (um), the exposure (ms) and the frame the camera sees there."""

    microscope: Microscope
    slide: str
    exposure_ms: float
    x_um: float = 0.0
    y_um: float = 0.0
    z_um: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.microscope.spec.shape

    def frame(self) -> np.ndarray:
        """The tile under the objective (its centre the nearest), seen where the stage
        stands (off the tile's centre: a lateral correction), at the focus stage's z:
        (height, width) uint16 counts, the simulator's green channel."""
        grid = self.microscope.slides[self.slide].grid
        row = round((self.y_um - grid.origin_y_um) / grid.pitch_um)
        col = round((self.x_um - grid.origin_x_um) / grid.pitch_um)
        x_um, y_um = grid.stage_xy_um(row, col)
        # The simulator's refusal (a stage off the slide, a focus out of range) is raised
        # as a C++ camera's failure reaches pymmcore: a RuntimeError, which the MMCore
        # backend reports as the camera's DeviceError.
        try:
            plan = self.microscope.plan(
                self.slide, row, col, self.z_um, 1.0, 1, self.exposure_ms / 1000.0,
                stage_offset_um=(self.x_um - x_um, self.y_um - y_um),
            )  # fmt: skip
        except AcquisitionRefusedError as refusal:
            raise RuntimeError(f"nothing to image here: {refusal}") from refusal
        (frame,) = self.microscope.render(plan)
        return frame[..., GREEN]


def simulated_core(microscope: Microscope, slide: str) -> UniMMCore:
    """A UniMMCore whose camera ("Camera"), XY stage ("XY") and focus stage ("Z") image
    `slide` of `microscope`."""
    exposure_ms = 1000.0 * microscope.spec.stage.timing.exposure_s
    return scope_core(SimulatedScope(microscope, slide, exposure_ms))


class SimulatedMMCoreInstrument(MMCoreInstrument):
    """The MMCore backend over `simulated_core(microscope, slide)`, with the simulator's
    grid, focus range and optics as its options (`options` gives the rest: timeouts,
    tolerances), the simulator's imaging conditions in its plans, and the simulator's
    truths (a `TruthSource` and a `PhaseTruthSource`)."""

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
        self.imaging = spec.imaging

    def truth(self, slide: str) -> FocusTruth:
        return self.simulator.truth(slide)

    def phase_truth(self, slide: str, row: int, col: int) -> TilePhase:
        return self.simulator.phase_truth(slide, row, col)

    def close(self) -> None:
        super().close()
        self.simulator.close()
