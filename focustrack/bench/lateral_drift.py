"""The second pass's lateral placement in `focustrack bench drift`, on the simulator.

A virtual tissue slide (`focustrack_instrument_sim.virtual_slide`, the simulated 60x
objective and camera) is imaged at `tiles` tiles of its middle row; the slide is then
moved on the stage by `offset_um` (the simulator's `--lateral-offset-x-um/-y-um`) and
the same tiles imaged again at their place. Their offset is measured as the scheduler
measures it (`focustrack_scheduler.realign`: phase correlation of each pair, the median
of the confident ones) and the stage sent by it (the requests' stage offset). The error
is where the simulator's stage really went for each corrected tile, less where the slide
lies on it (its truth), against the first pass's place, px; without the correction, the
slide's offset itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from focustrack_instrument_sim import simulated
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_scheduler.lateral import combined, grey, phase_shift


@dataclass(frozen=True)
class Placement:
    """The largest placement error of a pass's tiles (px) with the stage corrected, and
    without."""

    corrected_px: float
    uncorrected_px: float


def placement(
    seed: int, offset_um: tuple[float, float], tiles: int, tile_px: int, max_offset_um: float
) -> Placement:
    """One slide's second pass moved by `offset_um` (x, y): see the module docstring."""
    first = _instrument(seed, tiles, tile_px, (0.0, 0.0))
    second = _instrument(seed, tiles, tile_px, offset_um)
    try:
        places = [(1, col) for col in range(1, tiles + 1)]  # the middle row: tissue
        pixel_um = first.microscope.pixel_size_um
        shifts = [
            phase_shift(_frame(first, tile), _frame(second, tile), max_offset_um / pixel_um)
            for tile in places
        ]
        shift = combined(shifts, tiles // 2 + 1)
        correction_um = (0.0, 0.0) if shift is None else (
            shift.dx_px * pixel_um, shift.dy_px * pixel_um
        )  # fmt: skip
        slide_x_um, slide_y_um = second.truth("slide-0").lateral_offset_um
        errors_px = []
        for tile in places:
            at = second.microscope.plan("slide-0", *tile, 0.0, 1.0, 1)
            moved = second.microscope.plan(
                "slide-0", *tile, 0.0, 1.0, 1, stage_offset_um=correction_um
            )
            # the slide's place under the camera, against the first pass's (`at` less the
            # slide's offset would be it uncorrected)
            errors_px.append(
                np.hypot(
                    moved.stage_x_um - slide_x_um - at.stage_x_um,
                    moved.stage_y_um - slide_y_um - at.stage_y_um,
                )
                / pixel_um
            )
        uncorrected_px = float(np.hypot(slide_x_um, slide_y_um) / pixel_um)
        return Placement(float(max(errors_px)), uncorrected_px)
    finally:
        first.close()
        second.close()


def _instrument(
    seed: int, tiles: int, tile_px: int, offset_um: tuple[float, float]
) -> simulated.SimulatedInstrument:
    options = SimulatorOptions(
        seed=seed, rows=3, cols=tiles + 2, width=tile_px, height=tile_px, tissue_slide=True,
        lateral_offset_x_um=offset_um[0], lateral_offset_y_um=offset_um[1], workers=1,
    )  # fmt: skip
    return simulated.simulated_instrument(options)


def _frame(instrument: simulated.SimulatedInstrument, tile: tuple[int, int]) -> np.ndarray:
    """A tile's grey frame at its true focus."""
    microscope = instrument.microscope
    focus_um = float(microscope.slides["slide-0"].focus_um[tile])
    (pixels,) = microscope.render(microscope.plan("slide-0", *tile, focus_um, 1.0, 1))
    return grey(pixels)
