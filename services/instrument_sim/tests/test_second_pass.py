"""The simulator moves a slide for a second pass (`--z-offset-um`): the drift the
estimator's `kf-rescan` tracks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

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

    def similarity(a: np.ndarray, b: np.ndarray) -> float:
        """The correlation of the images' detail (the stroma's slow shading taken off)."""
        a, b = (image - ndimage.gaussian_filter(image, 4.0) for image in (a, b))
        return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])

    slide_um = (12 * 0.108333, 8 * 0.108333)  # x, y: 12 and 8 camera pixels
    first_plan, _, first = frame((0.0, 0.0), (0.0, 0.0))
    _, truth, moved = frame(slide_um, (0.0, 0.0))
    assert truth.lateral_offset_um == slide_um
    assert similarity(first, moved) < 0.5
    # what lay at pixel (y, x) lies at (y + 8, x + 12): the slide moved along +x and +y
    assert similarity(first[:-8, :-12], moved[8:, 12:]) > 0.8  # camera noise apart
    assert similarity(first[8:, 12:], moved[:-8, :-12]) < 0.5
    corrected_plan, _, corrected = frame(slide_um, slide_um)  # the stage follows the slide
    assert corrected_plan.stage_x_um - first_plan.stage_x_um == pytest.approx(slide_um[0])
    assert corrected_plan.stage_y_um - first_plan.stage_y_um == pytest.approx(slide_um[1])
    assert similarity(first, corrected) > 0.8  # the same view, other camera noise
