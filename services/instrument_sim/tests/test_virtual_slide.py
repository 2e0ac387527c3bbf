"""The continuous virtual slide: one section per seed, tiles that share their overlap pixel
for pixel, empty glass, dust on the coverslip above, folds, and the truth of each tile."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from focustrack_core.surfaces import family_spec
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec
from focustrack_instrument_sim.simulated import SimulatedInstrument, microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_instrument_sim.virtual_slide import TissueSlide, TissueSlideSpec, tissue_slides

SIZE = 128
PIXEL_UM = 0.108333


def _slide(seed: int = 3, size: int = 8, **spec: object) -> TissueSlide:
    (slide,) = tissue_slides(
        seed, 1, family_spec("standard", size, size), (SIZE, SIZE), PIXEL_UM,
        TissueSlideSpec(**spec),  # type: ignore[arg-type]
    )  # fmt: skip
    return slide


def test_neighbours_share_their_overlap_pixel_for_pixel() -> None:
    slide = _slide()
    shift_px = round(slide.grid.pitch_um / PIXEL_UM)
    assert shift_px == round(SIZE * 0.9)
    tissue = np.argwhere(slide.truth().tissue_share[:, :-1] > 0.5)
    row, col = (int(v) for v in tissue[0])
    left = slide.tile(row, col, (SIZE, SIZE), PIXEL_UM).section
    right = slide.tile(row, col + 1, (SIZE, SIZE), PIXEL_UM).section
    below = slide.tile(row + 1, col, (SIZE, SIZE), PIXEL_UM).section
    np.testing.assert_allclose(left[:, shift_px:], right[:, : SIZE - shift_px], atol=1e-6)
    np.testing.assert_allclose(left[shift_px:], below[: SIZE - shift_px], atol=1e-6)
    assert left[:, shift_px:].std() > 0.01  # tissue, not glass, was compared


def test_a_slide_has_tissue_empty_glass_dust_and_a_fold_and_each_seed_its_own() -> None:
    slide = _slide(size=10)
    truth = slide.truth()
    assert 0 < truth.empty.sum() < 50 and (truth.tissue_share > 0.9).sum() > 20
    assert np.isfinite(truth.dust_dz_um).sum() > 0
    assert np.isfinite(truth.fold_dz_um).sum() > 0
    dust = truth.dust_dz_um[np.isfinite(truth.dust_dz_um)]
    assert np.all((dust >= 10.0) & (dust <= 170.0))
    empty = np.argwhere(truth.empty)[0]
    glass = slide.tile(*(int(v) for v in empty), (SIZE, SIZE), PIXEL_UM).section
    assert glass.std() < 1e-3 and glass.min() > 0.95  # nothing to focus on
    other = _slide(seed=4, size=10).truth()
    assert not np.array_equal(truth.tissue_share, other.tissue_share)
    again = _slide(size=10).tile(5, 5, (SIZE, SIZE), PIXEL_UM)
    np.testing.assert_array_equal(again.section, slide.tile(5, 5, (SIZE, SIZE), PIXEL_UM).section)


def _variance_curve(scope: Microscope, row: int, col: int, z_um: np.ndarray) -> np.ndarray:
    step = float(z_um[1] - z_um[0])
    stack = scope.acquire("slide-0", row, col, float(z_um[0]), step, len(z_um))
    green = stack.pixels[..., 1].astype(np.float64)
    return green.var(axis=(1, 2)) / green.mean(axis=(1, 2))


def test_the_section_is_sharp_at_its_height_and_dust_makes_a_second_peak_above() -> None:
    slide = _slide(size=8, coverslip_above_um=(12.0, 12.0), dust_density=3000.0, folds=0)
    scope = Microscope([slide], MicroscopeSpec(height=SIZE, width=SIZE, workers=1))
    try:
        truth = slide.truth()
        tissue = np.isfinite(truth.dust_dz_um) & (truth.tissue_share > 0.8)
        row, col = (int(v) for v in np.argwhere(tissue)[0])
        focus_um = float(slide.focus_um[row, col])
        near = focus_um + np.arange(-2.0, 2.01, 0.25)
        curve = _variance_curve(scope, row, col, near)
        assert abs(near[int(np.argmax(curve))] - focus_um) <= 0.25
        wide = focus_um + np.arange(-4.0, 16.01, 1.0)
        curve = _variance_curve(scope, row, col, wide)
        assert abs(wide[int(np.argmax(curve))] - focus_um) <= 0.5
        # the dust: a second peak of its own, at its height
        dust = int(np.argmin(np.abs(wide - focus_um - truth.dust_dz_um[row, col])))
        assert curve[dust] > 1.5 * max(curve[dust - 3], curve[dust + 3])
        assert curve[dust] >= curve[dust - 1] and curve[dust] >= curve[dust + 1]
    finally:
        scope.close()


def test_the_simulator_serves_virtual_slides_and_their_truth() -> None:
    options = SimulatorOptions(tissue_slide=True, rows=5, cols=6, width=SIZE, height=SIZE, seed=2)
    instrument = SimulatedInstrument(microscope_from_options(options))
    try:
        (layout,) = instrument.describe().slides
        pixel_um = instrument.describe().optics.pixel_size_um
        assert layout.grid.pitch_um == pytest.approx(round(SIZE * 0.9) * pixel_um)
        truth = instrument.truth("slide-0")
        assert truth.tiles is not None and truth.tiles.empty.shape == (5, 6)
        dust = np.isfinite(truth.tiles.dust_z_um)
        assert np.all(truth.tiles.dust_z_um[dust] > truth.best_focus_um[dust] + 9.9)
    finally:
        instrument.close()


@pytest.mark.parametrize("overlap", [-0.1, 0.5])
def test_an_overlap_outside_its_range_is_refused(overlap: float) -> None:
    with pytest.raises(ValidationError, match="overlap"):
        SimulatorOptions(tissue_slide=True, overlap=overlap)
    with pytest.raises(ValueError, match="overlap"):
        TissueSlideSpec(overlap=overlap)
