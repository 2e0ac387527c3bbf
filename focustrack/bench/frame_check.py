"""The second pass's first-frame check in `focustrack bench drift`, on the simulator's images.

The replay (`focustrack_estimator.replay`) has no images, so the check is made on frames
of the simulator rendered beforehand (`sharpness_table`): `textures` tiles of a virtual
tissue slide (`focustrack_instrument_sim.virtual_slide`, the simulated 60x / 0.85
objective and camera, `tile_px` square), each rendered at defocus -`MAX_DZ_UM` to
+`MAX_DZ_UM` every `DZ_STEP_UM`, `DRAWS` times (the camera's noise drawn anew), each
frame's sharpness kept (`focustrack_scheduler.focus_check.sharpness`, the scheduler's).

A tile of a map is one of those textures (its row-major index modulo their number). Its
first pass's image is a frame at the defocus of that pass's kept image (its `z_used_um`
less its truth when imaged), the second pass's a frame at its own (the frame's z less the
truth now), each a draw at random, at the nearest defocus rendered: the second's sharpness
over the first's against `min_ratio` is the scheduler's rule (`focus_check.out_of_focus`).
The stage is taken as corrected (the pass's lateral offset known): both show the same
place, as the scheduler's comparison does once it has moved the stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from focustrack_instrument_sim import simulated
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_scheduler.focus_check import out_of_focus, sharpness
from focustrack_scheduler.lateral import grey

#: The defocus rendered, um: +/- this (a frame farther off is as unsharp as there: far
#: below any `min_ratio`), every `DZ_STEP_UM` (over which sharpness moves by 1% at most).
MAX_DZ_UM = 2.0
DZ_STEP_UM = 0.02
#: Frames rendered at each defocus of each texture, their camera noise drawn anew.
DRAWS = 2


@dataclass(frozen=True)
class SharpnessTable:
    """The sharpness of simulated frames: (textures, defocus, draws), at `dz_um` (um)."""

    dz_um: np.ndarray
    sharpness: np.ndarray

    def draw(self, texture: int, dz_um: float, rng: np.random.Generator) -> float:
        """The sharpness of a frame of `texture` at defocus `dz_um` (the nearest rendered),
        one of its draws at random."""
        i = int(np.clip(np.rint((dz_um - self.dz_um[0]) / DZ_STEP_UM), 0, self.dz_um.size - 1))
        return float(self.sharpness[texture, i, rng.integers(self.sharpness.shape[2])])


def sharpness_table(seed: int, textures: int, tile_px: int) -> SharpnessTable:
    """The simulator's frames' sharpness (module docstring): the middle row's tiles of a
    virtual tissue slide of `seed` (tissue), `tile_px` square."""
    options = SimulatorOptions(
        seed=seed, rows=3, cols=textures + 2, width=tile_px, height=tile_px, tissue_slide=True,
        workers=1,
    )  # fmt: skip
    instrument = simulated.simulated_instrument(options)
    try:
        microscope = instrument.microscope
        renderer = microscope.renderer
        frame = np.empty(microscope.spec.frame.shape, dtype=microscope.spec.frame.dtype)
        rng = np.random.default_rng([seed, 23])
        steps = round(MAX_DZ_UM / DZ_STEP_UM)
        dz_um = np.arange(-steps, steps + 1) * DZ_STEP_UM
        values = np.empty((textures, dz_um.size, DRAWS))
        for texture in range(textures):
            plan = microscope.plan("slide-0", 1, texture + 1, 0.0, 1.0, 1)
            for i, dz in enumerate(dz_um):
                for k in range(DRAWS):
                    renderer.render_frame(plan.tile, float(dz), plan.exposure_s, rng, frame)
                    values[texture, i, k] = sharpness(grey(frame))
        return SharpnessTable(dz_um, values)
    finally:
        instrument.close()


class SimulatedFrameCheck:
    """The scheduler's first-frame check on one map (`focustrack_estimator.replay.FrameCheck`):
    `reference_dz_um` (rows, cols) is each tile's first-pass image's defocus, um."""

    def __init__(
        self, table: SharpnessTable, reference_dz_um: np.ndarray, min_ratio: float, seed: int
    ) -> None:
        self.table = table
        self.reference_dz_um = reference_dz_um
        self.min_ratio = min_ratio
        self.rng = np.random.default_rng([seed, 29])

    def __call__(self, row: int, col: int, z_um: float, truth_um: float) -> bool:
        textures = self.table.sharpness.shape[0]
        texture = (row * self.reference_dz_um.shape[1] + col) % textures
        frame = self.table.draw(texture, z_um - truth_um, self.rng)
        reference = self.table.draw(texture, float(self.reference_dz_um[row, col]), self.rng)
        return out_of_focus(frame / reference, self.min_ratio)
