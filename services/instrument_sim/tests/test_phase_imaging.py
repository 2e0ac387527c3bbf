"""Phase specimens and their partially coherent imaging, without Zenoh: the specimens'
phase, Abbe's image formation against a direct reference, the physics of defocus contrast,
and the microscope's phase stacks, plans and truth."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.surfaces import SurfaceSpec
from focustrack_instrument_sim import optics as opt
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    ImagingConditions,
    Purpose,
    Refusal,
)
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, slides_from_seed
from focustrack_instrument_sim.phase_specimen import (
    PhaseObject,
    PhaseSpecimenSpec,
    cell_culture,
    evans_fung_um,
    red_cells,
)
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_instrument_sim.stage import StageSpec

SPEC = PhaseSpecimenSpec()
PIXEL_UM = opt.Optics().pixel_size_um
WAVELENGTH_UM = opt.Illumination().wavelength_um


def _tile(specimen, index: int, size: int = 256) -> PhaseObject:
    return specimen(SPEC, np.random.SeedSequence([7, index]), (size, size), PIXEL_UM)


def _imager(condenser_na: float, shape: tuple[int, int]) -> opt.AbbeImager:
    return opt.AbbeImager(opt.Optics(), opt.Illumination(condenser_na=condenser_na), shape)


def _pure_phase(obj: PhaseObject) -> np.ndarray:
    """The specimen's transmittance without its (weak) absorption."""
    return np.exp(1j * obj.phase_rad(WAVELENGTH_UM)).astype(np.complex64)


def test_a_red_cell_is_a_biconcave_disc_of_the_textbook_thickness() -> None:
    rho = np.linspace(0.0, 1.0, 1001)
    thickness_um = evans_fung_um(rho)
    assert thickness_um[0] == pytest.approx(0.81)
    assert 2.4 < thickness_um.max() < 2.7 and 0.6 < rho[np.argmax(thickness_um)] < 0.8
    assert thickness_um[-1] == 0.0


@pytest.mark.parametrize("specimen", [cell_culture, red_cells])
def test_a_phase_specimen_is_the_same_every_time_and_differs_between_tiles(specimen) -> None:
    first, again, other = _tile(specimen, 1), _tile(specimen, 1), _tile(specimen, 2)
    np.testing.assert_array_equal(first.opd_um, again.opd_um)
    np.testing.assert_array_equal(first.density, again.density)
    assert not np.array_equal(first.opd_um, other.opd_um)
    t = first.transmittance(WAVELENGTH_UM)
    assert t.dtype == np.complex64 and t.shape == (256, 256)
    np.testing.assert_allclose(np.angle(t), np.angle(np.exp(1j * first.phase_rad(WAVELENGTH_UM))),
                               atol=1e-4)  # fmt: skip


def test_cells_in_culture_have_the_phase_of_their_index_and_thickness() -> None:
    """phi = 2 pi (n_cell - n_medium) h / lambda: 0.3-1 rad over cytoplasm (dn 0.025-0.045,
    h 1-2 um), 1-2.5 rad over nuclei and nucleoli; absorption is weak."""
    tiles = [_tile(cell_culture, index, 512) for index in range(8)]
    phase = np.stack([tile.phase_rad(WAVELENGTH_UM) for tile in tiles])
    cells = phase > 0.05
    assert phase.min() >= 0 and 0.1 < cells.mean() < 0.8
    assert 0.3 < np.median(phase[cells]) < 1.2
    assert 1.2 < np.percentile(phase[cells], 99) < 3.0
    amplitude = np.exp(-0.5 * np.stack([tile.density for tile in tiles]))
    assert amplitude.min() > 0.95  # |t| >= 0.95: nearly transparent


def test_red_cells_are_phase_discs_brighter_at_the_rim() -> None:
    """dn = 1.39-1.41 - 1.345, thickness 2.2-2.6 um at the rim, 0.7-0.8 um in the centre."""
    tiles = [_tile(red_cells, index, 512) for index in range(8)]
    phase = np.stack([tile.phase_rad(WAVELENGTH_UM) for tile in tiles])
    cells = phase > 0.05
    assert 0.1 < cells.mean() < 0.8
    rim = np.percentile(phase[cells], 95)
    assert 1.2 < rim < 2.3  # 2 pi 0.055 2.4 / 0.532 = 1.56 rad
    assert np.percentile(phase[cells], 10) < 0.5 * rim  # the central pallor
    assert np.exp(-0.5 * np.stack([tile.density for tile in tiles])).min() > 0.95


@pytest.mark.parametrize(
    ("condenser_na", "magnification", "grid"),
    [(0.0, 60.0, (48, 64)), (0.3, 60.0, (36, 48)), (0.3, 20.0, (48, 64))],
)
def test_abbe_imaging_is_the_sum_over_tilted_coherent_images(
    condenser_na: float, magnification: float, grid: tuple[int, int]
) -> None:
    """The imager against the formula, in plain numpy on the frame's grid: for each source
    point s, IFFT(FFT(t exp(i 2 pi s.x)) P(f) exp(-i pi lambda dz |f|^2)), intensities
    summed. With 19 source points at 60x the imager's fields are on a coarser grid
    (`grid`); coherent light (one point) and 20x (pixels too coarse for the intensity's
    band) use the frame's."""
    shape, dz_um = (48, 64), 1.7
    optics = opt.Optics(magnification=magnification)
    pixel_um = optics.pixel_size_um
    rng = np.random.default_rng(3)
    t = (np.exp(1j * rng.normal(0, 0.6, shape)) * rng.uniform(0.8, 1.0, shape)).astype(np.complex64)
    illumination = opt.Illumination(condenser_na=condenser_na)
    imager = opt.AbbeImager(optics, illumination, shape)
    assert imager.grid == grid
    ours = imager.intensity(imager.spectrum(t), dz_um)
    fy, fx = np.fft.fftfreq(shape[0], pixel_um), np.fft.fftfreq(shape[1], pixel_um)
    f_sq = fy[:, None] ** 2 + fx[None, :] ** 2
    pupil = f_sq <= (optics.numerical_aperture / WAVELENGTH_UM) ** 2
    defocus = np.exp(-1j * np.pi * WAVELENGTH_UM * dz_um * f_sq)
    y_um = (np.arange(shape[0]) * pixel_um)[:, None]
    x_um = (np.arange(shape[1]) * pixel_um)[None, :]
    offsets, weights = opt.source_offsets(illumination, shape, pixel_um)
    assert (len(offsets) == 1) == (condenser_na == 0) and weights.sum() == pytest.approx(1.0)
    reference = np.zeros(shape)
    for (dv, du), weight in zip(offsets, weights, strict=True):
        sy_per_um, sx_per_um = dv / (shape[0] * pixel_um), du / (shape[1] * pixel_um)
        tilt = np.exp(2j * np.pi * (sy_per_um * y_um + sx_per_um * x_um))
        field = np.fft.ifft2(np.fft.fft2(t * tilt) * pupil * defocus)
        reference += weight * np.abs(field) ** 2
    assert ours.dtype == np.float32 and ours.shape == shape
    np.testing.assert_allclose(ours, reference, atol=2e-5)


def test_the_condenser_is_sampled_evenly_within_its_aperture() -> None:
    illumination = opt.Illumination(condenser_na=0.4)
    shape = (512, 512)
    offsets, weights = opt.source_offsets(illumination, shape, PIXEL_UM)
    assert len(offsets) == 19 and np.allclose(weights, 1 / 19)  # 1 + 6 + 12, none merged
    radius_per_um = np.hypot(*offsets.T) / (512 * PIXEL_UM)
    assert radius_per_um.max() <= illumination.condenser_na / illumination.wavelength_um
    assert np.abs(offsets.mean(axis=0)).max() < 0.5  # centred: no net tilt
    tiny, _ = opt.source_offsets(opt.Illumination(condenser_na=0.001), shape, PIXEL_UM)
    assert len(tiny) == 1  # a condenser narrower than a frequency step: a point source


def test_a_pure_phase_object_in_focus_is_almost_invisible_in_coherent_light() -> None:
    """In focus, |t|^2 = 1 and the pupil only cuts what the objective cannot take: the
    image is nearly uniform; defocus turns phase into intensity contrast, growing with
    |dz| over the first micrometres, either side of focus."""
    t = _pure_phase(_tile(red_cells, 3))
    imager = _imager(0.0, t.shape)
    spectrum_t = imager.spectrum(t)
    contrast = {dz: float(imager.intensity(spectrum_t, dz).std()) for dz in (0, 0.5, 1, 2, -2)}
    assert contrast[0] < 0.25 * contrast[2]
    assert contrast[0] < contrast[0.5] < contrast[1] < contrast[2]
    assert contrast[-2] == pytest.approx(contrast[2], rel=0.2)
    # the sign of the contrast flips through focus (the transport of intensity equation)
    above = imager.intensity(spectrum_t, 1.0) - 1.0
    below = imager.intensity(spectrum_t, -1.0) - 1.0
    assert np.corrcoef(above.ravel(), below.ravel())[0, 1] < -0.5


def test_partial_coherence_lowers_the_defocus_contrast_of_fine_detail() -> None:
    """Tilted plane waves shift a defocused image by lambda dz s: their sum blurs detail
    finer than about 1 / (dz condenser_na)."""
    obj = _tile(cell_culture, 1, 512)
    assert (obj.opd_um > 0).mean() > 0.1  # cells, not empty medium
    t = _pure_phase(obj)
    fy, fx = np.fft.fftfreq(t.shape[0], PIXEL_UM), np.fft.fftfreq(t.shape[1], PIXEL_UM)
    frequency = np.hypot(fy[:, None], fx[None, :])
    fine = (frequency > 0.6) & (frequency < 1.5)  # cycles/um
    power = {}
    for condenser_na in (0.0, 0.4):
        imager = _imager(condenser_na, t.shape)
        image = imager.intensity(imager.spectrum(t), 3.0)
        power[condenser_na] = float((np.abs(np.fft.fft2(image - image.mean())) ** 2)[fine].sum())
    assert power[0.4] < 0.5 * power[0.0]


@pytest.mark.parametrize("condenser_na", [0.0, 0.2])
def test_defocus_keeps_the_light(condenser_na: float) -> None:
    """|exp(-i pi lambda dz f^2)| = 1: the mean intensity does not depend on defocus."""
    obj = _tile(red_cells, 1)
    imager = _imager(condenser_na, obj.opd_um.shape)
    spectrum_t = imager.spectrum(obj.transmittance(WAVELENGTH_UM))
    means = [float(imager.intensity(spectrum_t, dz).mean(dtype=np.float64)) for dz in (-6, 0, 3)]
    np.testing.assert_allclose(means, means[1], rtol=1e-4)
    assert 0.9 < means[1] <= 1.0  # weak absorption and light scattered beyond the pupil


def _phase_scope(kind: str = "phase-cells", seed: int = 4, **spec) -> Microscope:
    spec = {"height": 128, "width": 128, "specimen_kind": kind, **spec}
    return Microscope(slides_from_seed(seed, 1, SurfaceSpec(2, 3)), MicroscopeSpec(**spec), seed=1)


def test_a_phase_stack_is_monochrome_reproducible_and_least_contrasted_at_focus() -> None:
    stacks = []
    for _ in range(2):
        scope = _phase_scope("phase-blood")  # half of tile (0, 0) is red cells
        truth_um = float(scope.slides["slide-0"].focus_um[0, 0])
        stacks.append(scope.acquire("slide-0", 0, 0, truth_um - 3.0, 0.25, 25))
        scope.close()
    pixels = stacks[0].pixels
    np.testing.assert_array_equal(pixels, stacks[1].pixels)  # seed for seed, noise included
    np.testing.assert_array_equal(pixels[..., 0], pixels[..., 1])  # one wavelength
    np.testing.assert_array_equal(pixels[..., 2], pixels[..., 1])
    contrast = pixels[..., 1].astype(float).std(axis=(1, 2))
    assert abs(stacks[0].z_um[np.argmin(contrast)] - truth_um) <= 0.25
    assert contrast.max() > 3 * contrast.min()
    camera = scope.spec.camera  # clear glass at 60% of the well, as the stained smear's
    mean_adu = pixels.mean(dtype=np.float64)
    expected_adu = camera.background_e_per_s * 0.01 / camera.gain_e_per_adu + camera.offset_adu
    assert mean_adu == pytest.approx(expected_adu, rel=0.05)


def test_a_plan_says_what_the_stack_is_for_and_how_it_is_imaged() -> None:
    scope = _phase_scope("phase-blood")
    plan = scope.plan("slide-0", 1, 2, -2.0, 0.5, 3, purpose=Purpose.PHASE, reference_z_um=-1.0)
    assert (plan.purpose, plan.reference_z_um) == (Purpose.PHASE, -1.0)
    assert plan.imaging == ImagingConditions(
        wavelength_um=0.532, condenser_na=0.2, objective_na=0.85, photons_per_count=5.0,
        dark_counts=100.0,
    )  # fmt: skip
    focus = scope.plan("slide-0", 1, 2, -2.0, 0.5, 3)
    assert (focus.purpose, focus.imaging) == (Purpose.FOCUS, plan.imaging)
    scope.close()
    stained = Microscope(
        slides_from_seed(4, 1, SurfaceSpec(2, 3)), MicroscopeSpec(height=64, width=64)
    )
    imaging = stained.plan("slide-0", 0, 0, 0.0, 1.0, 1).imaging
    stained.close()
    # incoherent imaging of the stained smear: the condenser filled to the objective's NA
    assert (imaging.wavelength_um, imaging.condenser_na, imaging.objective_na) == (0.55, 0.85, 0.85)


@pytest.mark.parametrize(
    ("reference_z_um", "reason"),
    [
        (150.0, Refusal.Z_OUT_OF_RANGE),
        (-150.0, Refusal.Z_OUT_OF_RANGE),
        (np.nan, Refusal.MALFORMED),
    ],
)
def test_a_phase_stack_to_be_reconstructed_beyond_the_travel_is_refused(
    reference_z_um: float, reason: Refusal
) -> None:
    scope = _phase_scope()
    clock_s = scope.stage.clock_s
    with pytest.raises(AcquisitionRefusedError) as refused:
        scope.plan("slide-0", 0, 0, 0.0, 1.0, 3, purpose=Purpose.PHASE,
                   reference_z_um=reference_z_um)  # fmt: skip
    assert (refused.value.reason, refused.value.field) == (reason, "reference_z_um")
    assert scope.stage.clock_s == clock_s  # the stage did not move
    # a focus stack does not reconstruct: its reference is not checked
    scope.plan("slide-0", 0, 0, 0.0, 1.0, 3, reference_z_um=reference_z_um)
    scope.close()


def test_the_true_phase_is_the_imaged_specimens_and_refuses_what_is_not_there() -> None:
    scope = _phase_scope("phase-blood")
    truth = scope.true_phase("slide-0", 1, 0)
    seed = np.random.SeedSequence([4, 0, 1, 0]).spawn(2)[0]  # the slide's seed, the tile's
    expected = red_cells(SPEC, seed, (128, 128), PIXEL_UM).phase_rad(WAVELENGTH_UM)
    np.testing.assert_array_equal(truth.phase_rad, expected)
    assert truth.phase_rad.dtype == np.float32 and truth.pixel_size_um == PIXEL_UM
    assert truth.focus_z_um == pytest.approx(float(scope.slides["slide-0"].focus_um[1, 0]))
    with pytest.raises(AcquisitionRefusedError) as unknown:
        scope.true_phase("slide-9", 0, 0)
    assert unknown.value.reason is Refusal.UNKNOWN_SLIDE
    with pytest.raises(AcquisitionRefusedError) as outside:
        scope.true_phase("slide-0", 0, 3)
    assert (outside.value.reason, outside.value.field) == (Refusal.TILE_OUTSIDE_SLIDE, "col")
    scope.close()
    stained = _phase_scope("stained-smear")
    assert not stained.true_phase("slide-0", 0, 0).phase_rad.any()  # a pure absorber
    stained.close()


@pytest.mark.parametrize(("specimen", "defocus_um"), [("stained-smear", 0.0), ("phase-cells", 3.0)])
def test_a_tile_with_no_specimen_in_view_shows_a_field_of_noise_alone(
    specimen: str, defocus_um: float
) -> None:
    """A smear's empty fields (plasma alone) and the glass between cells in culture are
    not in view; their frames (a phase object's out of focus, where it shows) are as flat
    as the camera's noise leaves them, those of a tile in view are not."""
    options = SimulatorOptions(seed=2, rows=4, cols=4, width=128, height=128, specimen=specimen)
    scope = microscope_from_options(options)
    in_view = np.array(
        [[scope.specimen_in_view("slide-0", r, c) for c in range(4)] for r in range(4)]
    )
    assert in_view.any() and not in_view.all()
    focus_um, _ = scope.truth_um("slide-0")

    def spread(tile: tuple[int, int]) -> float:  # the frame's std over its mean
        z_um = float(focus_um[tile]) + defocus_um
        frame = scope.acquire("slide-0", *tile, z_um, 1.0, 1).pixels[0].astype(np.float64)
        return float(frame.std() / frame.mean())

    empty = tuple(np.argwhere(~in_view)[0])
    full = tuple(np.argwhere(in_view)[0])
    assert spread(full) > 5 * spread(empty)
    with pytest.raises(AcquisitionRefusedError):
        scope.specimen_in_view("slide-0", 4, 0)
    scope.close()


def test_the_true_focus_of_the_phase_truth_drifts() -> None:
    scope = _phase_scope(stage=StageSpec(drift_um_per_s=0.01))
    scope.acquire("slide-0", 0, 0, 0.0, 0.5, 5)
    truth_um, drift_um = scope.truth_um("slide-0")
    assert drift_um > 0
    assert scope.true_phase("slide-0", 0, 0).focus_z_um == pytest.approx(float(truth_um[0, 0]))
    scope.close()


def test_the_options_choose_the_specimen_and_the_condenser() -> None:
    options = SimulatorOptions(specimen="phase-blood", condenser_na=0.0, width=64, height=64)
    scope = microscope_from_options(options)
    scope.close()
    assert scope.spec.specimen_kind == "phase-blood" and scope.spec.illumination.condenser_na == 0
    assert scope.spec.imaging.condenser_na == 0.0  # coherent
    with pytest.raises(ValueError, match="must not exceed the objective's"):
        microscope_from_options(SimulatorOptions(condenser_na=0.9))
    with pytest.raises(ValueError, match="specimen must be one of"):
        MicroscopeSpec(specimen_kind="stained-cells")
