"""A look (one frame) tells empty glass from tissue on the virtual slides of the instrument
simulator: the focus service's answer that lets a scan image empty glass with one frame."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.pipeline import FocusSettings, FrameByFrame, focus_stack
from focustrack_focus.preprocess import Preprocess, lowpass_sigma_for_optics
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions


@pytest.mark.parametrize("seed", [3, 4])  # not the seeds the threshold was chosen on (1, 2)
def test_a_look_tells_empty_glass_from_tissue(seed: int) -> None:
    options = SimulatorOptions(
        tissue_slide=True, seed=seed, slides=1, rows=6, cols=6, width=256, height=256
    )
    microscope = microscope_from_options(options)
    slide = microscope.slides["slide-0"]
    truth = slide.truth()
    optics = microscope.spec.optics
    pixel_um, na = optics.pixel_size_um, optics.numerical_aperture
    settings = FocusSettings(Preprocess(lowpass_sigma_px=lowpass_sigma_for_optics(pixel_um, na)))
    called_empty = np.zeros(slide.grid.shape, dtype=bool)
    stained = np.zeros(slide.grid.shape, dtype=bool)  # any pixel of section in view
    for row in range(slide.grid.rows):
        for col in range(slide.grid.cols):
            z_um = float(slide.focus_um[row, col]) + 0.7  # a prediction 0.7 um off
            layers = slide.tile(row, col, (256, 256), pixel_um)
            stained[row, col] = layers.section.min() < 0.95 or layers.fold is not None
            frame = next(
                iter(microscope.render(microscope.plan("slide-0", row, col, z_um, 0.5, 1)))
            )
            result = focus_stack(frame[None], np.array([z_um]), settings)
            assert result.best_z_um is None and result.sigma_um is None
            called_empty[row, col] = FocusFlag.EMPTY in result.flags
            if called_empty[row, col]:
                assert result.flags == {FocusFlag.EMPTY, FocusFlag.FLAT}
            else:
                assert not result.flags
            # the Zenoh path reads the frame as it comes, to the same answer
            curve = FrameByFrame(np.array([z_um]), settings)
            curve.add(0, frame)
            assert curve.result().flags == result.flags
    # glass: no pixel of section (a cell's edge in a corner is one), dust and bubbles may be
    glass = ~stained
    assert glass.any() and called_empty[glass].all()
    # a sliver of tissue (under 1% of the tile) may pass for glass or not; more never does
    assert not called_empty[truth.tissue_share >= 0.01].any()
