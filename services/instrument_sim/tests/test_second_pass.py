"""The simulator moves a slide for a second pass (`--z-offset-um`): the drift the
estimator's `kf-rescan` tracks."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_instrument_sim import simulated
from focustrack_instrument_sim.simulator_options import SimulatorOptions


def test_the_simulator_moves_a_slide_for_a_second_pass() -> None:
    def truth(z_offset_um: float = 0.0) -> np.ndarray:
        options = SimulatorOptions(rows=3, cols=4, width=32, height=32, z_offset_um=z_offset_um)
        microscope = simulated.microscope_from_options(options)
        return microscope.truth_um("slide-0")[0]

    assert np.allclose(truth(12.0) - truth(), 12.0)


def test_a_slide_moved_on_the_stage_is_seen_where_the_stage_goes() -> None:
    """`--lateral-offset-x-um`/`-y-um` move the slide; a request's stage offset moves the
    stage: the frames show the slide where the stage went, less where the slide lies."""
    from focustrack_scheduler.lateral import phase_shift

    def frame(slide_offset_um: tuple[float, float], stage_offset_um: tuple[float, float]):
        options = SimulatorOptions(
            rows=2, cols=2, width=128, height=128, tissue_slide=True, seed=5,
            lateral_offset_x_um=slide_offset_um[0], lateral_offset_y_um=slide_offset_um[1],
        )  # fmt: skip
        instrument = simulated.simulated_instrument(options)
        plan = instrument.microscope.plan(
            "slide-0", 0, 1, 0.0, 1.0, 1, stage_offset_um=stage_offset_um
        )
        truth = instrument.truth("slide-0")
        (pixels,) = instrument.microscope.render(plan)
        instrument.close()
        return plan, truth, pixels[..., 1].astype(float)

    _, _, first = frame((0.0, 0.0), (0.0, 0.0))
    moved_plan, truth, moved = frame((1.3, 0.9), (0.0, 0.0))
    assert truth.lateral_offset_um == (1.3, 0.9)
    pixel_um = moved_plan.pixel_size_um
    shift = phase_shift(first, moved, max_shift_px=30)  # the slide moved by (x 1.3, y 0.9) um
    assert shift.dx_px * pixel_um == pytest.approx(1.3, abs=0.03)
    assert shift.dy_px * pixel_um == pytest.approx(0.9, abs=0.03)
    corrected_plan, _, corrected = frame((1.3, 0.9), (1.3, 0.9))
    x_um, y_um = corrected_plan.stage_x_um, corrected_plan.stage_y_um
    assert (x_um - moved_plan.stage_x_um, y_um - moved_plan.stage_y_um) == pytest.approx(
        (1.3, 0.9)
    )
    back = phase_shift(first, corrected, max_shift_px=30)  # the stage followed: no shift left
    assert abs(back.dx_px) < 0.1 and abs(back.dy_px) < 0.1
