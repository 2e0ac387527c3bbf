"""A look (one frame) tells empty glass from tissue on the virtual slides of the instrument
simulator, at any defocus within a slide's range and with the coverslip's dust in view (in
focus or not): the focus service's answer that lets a scan image empty glass with one frame
wherever it lies, its height known or not."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusSettings, FrameByFrame, focus_stack
from focustrack_focus.preprocess import Preprocess, lowpass_sigma_for_optics
from focustrack_instrument_sim.microscope import Microscope
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions

#: Where the frames lie from the section, um: near focus, and 10 um either way (a slide's
#: first tile, its height unknown); each tile is looked at from one of them, in turn.
DEFOCUS_UM = (-10.0, 0.7, 10.0)


@pytest.mark.parametrize("seed", [3, 4])  # not the seeds the threshold was chosen on (1, 2)
def test_a_look_tells_empty_glass_from_tissue_at_any_defocus(seed: int) -> None:
    options = SimulatorOptions(
        tissue_slide=True, seed=seed, slides=1, rows=8, cols=8, width=256, height=256
    )
    simulated = microscope_from_options(options)
    # the same slide, on a stage whose travel reaches any tile's dust (up to 170 um above)
    spec = simulated.spec
    wide = replace(spec, stage=replace(spec.stage, z_range_um=(-300.0, 300.0)))
    microscope = Microscope(list(simulated.slides.values()), wide, seed=seed)
    slide = microscope.slides["slide-0"]
    truth = slide.truth()
    optics = microscope.spec.optics
    pixel_um, na = optics.pixel_size_um, optics.numerical_aperture
    settings = FocusSettings(Preprocess(lowpass_sigma_px=lowpass_sigma_for_optics(pixel_um, na)))
    shape = (*slide.grid.shape, 2)
    called_empty = np.zeros(shape, dtype=bool)
    for row in range(slide.grid.rows):
        for col in range(slide.grid.cols):
            dust_um = float(truth.dust_dz_um[row, col])  # NaN: no dust in view
            defocus_um = DEFOCUS_UM[(row + col) % len(DEFOCUS_UM)]
            # and its dust in focus, where it has dust in view
            heights = (defocus_um, dust_um if np.isfinite(dust_um) else defocus_um)
            for k, dz_um in enumerate(heights):
                z_um = float(slide.focus_um[row, col]) + dz_um
                plan = microscope.plan("slide-0", row, col, z_um, 0.5, 1)
                frame = next(iter(microscope.render(plan)))
                result = focus_stack(frame[None], np.array([z_um]), settings)
                assert result.best_z_um is None and result.sigma_um is None
                called_empty[row, col, k] = FocusFlag.EMPTY in result.flags
                if called_empty[row, col, k]:
                    assert result.flags == {FocusFlag.EMPTY, FocusFlag.FLAT}
                else:
                    assert not result.flags
                if k == 0:  # the Zenoh path reads the frame as it comes, to the same answer
                    curve = FrameByFrame(np.array([z_um]), settings)
                    curve.add(0, frame)
                    assert curve.result().flags == result.flags
    # glass: no section at any of the truth's 48 x 48 samples; dust and bubbles may be there
    glass = truth.tissue_share == 0.0
    assert glass.any() and called_empty[glass].all()
    # a tile with dust in view, in focus or not, read as glass at every height
    assert (np.isfinite(truth.dust_dz_um) & called_empty.all(axis=2)).any()
    # a sliver of tissue (under the 0.2% the truth calls empty) may pass for glass or not;
    # more never does, at any of these distances
    assert not called_empty[~truth.empty].any()


@pytest.mark.parametrize(("specimen", "seed"), [("phase-blood", 0), ("phase-cells", 4)])
def test_in_valley_mode_a_look_at_unstained_cells_reads_their_brightness(
    specimen: str, seed: int
) -> None:
    """Unstained cells have no stain for the look to see: in max mode every look at them
    in focus reads empty (a scan would give up each such tile unmeasured). In valley mode,
    the mode for such specimens, a look reads the frame's brightness: empty where the tile
    shows no cell (glass), in view where it does, in focus (where a phase object is
    faintest) and out of it, on both of the focus service's paths."""
    options = SimulatorOptions(
        seed=seed, slides=1, rows=5, cols=5, width=256, height=256, specimen=specimen
    )
    microscope = microscope_from_options(options)
    slide = microscope.slides["slide-0"]
    optics = microscope.spec.optics
    preprocess = Preprocess(
        lowpass_sigma_px=lowpass_sigma_for_optics(optics.pixel_size_um, optics.numerical_aperture)
    )
    max_mode = FocusSettings(preprocess)
    valley_mode = FocusSettings(preprocess, peak=PeakSettings(mode=PeakMode.VALLEY))
    empty = {FocusFlag.EMPTY, FocusFlag.FLAT}
    in_view = np.zeros(slide.grid.shape, dtype=bool)
    for row in range(slide.grid.rows):
        for col in range(slide.grid.cols):
            in_view[row, col] = microscope.specimen_in_view("slide-0", row, col)
            for dz_um in (0.0, -0.8):
                z_um = float(slide.focus_um[row, col]) + dz_um
                plan = microscope.plan("slide-0", row, col, z_um, 0.5, 1)
                frame = next(iter(microscope.render(plan)))[None]
                if dz_um == 0.0:
                    assert focus_stack(frame, np.array([z_um]), max_mode).flags == empty
                valley = focus_stack(frame, np.array([z_um]), valley_mode)
                assert valley.best_z_um is None
                assert valley.flags == (frozenset() if in_view[row, col] else empty)
                curve = FrameByFrame(np.array([z_um]), valley_mode)  # the Zenoh path alike
                curve.add(0, frame[0])
                assert curve.result().flags == valley.flags
    assert in_view.any() and not in_view.all()  # both kinds of tile were looked at
