"""The phase anchored to the empty background: the mask, the band's least squares, and what
it does to the filter's field on partially coherent stacks of a red-cell smear."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy import fft

from focustrack_phase import acekf, background, simulate
from focustrack_phase.propagation import frequency_sq_per_um2, phase_transfer_power

WAVELENGTH_UM = 0.532
PIXEL_UM = 1.0
Z_UM = np.arange(1, 21) * 2.5
CONDENSER_NA = 0.05


@functools.cache  # the Abbe simulation is most of each test's time
def _smear(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A 64 px smear of red cells (1 rad) and its partially coherent stack at 1000 photons."""
    truth = simulate.weak_object(64, seed=seed, peak_phase_rad=1.0)
    stack = simulate.partially_coherent_stack(
        truth, Z_UM, WAVELENGTH_UM, PIXEL_UM, 1e3, CONDENSER_NA, seed=seed
    )
    return truth, stack


def _reconstruct(stack: np.ndarray, anchor: acekf.Background) -> acekf.FieldEstimate:
    options = acekf.AcekfOptions(condenser_na=CONDENSER_NA, background=anchor)
    return acekf.reconstruct(stack, Z_UM, WAVELENGTH_UM, PIXEL_UM, options=options)


def _low_frequency_rmse(error_rad: np.ndarray, below_per_um: float = 0.05) -> float:
    spectrum = fft.fft2(error_rad - error_rad.mean(), norm="ortho")
    low = frequency_sq_per_um2(error_rad.shape, PIXEL_UM) < below_per_um**2
    return float(np.sqrt(np.sum(np.abs(spectrum[low]) ** 2) / error_rad.size))


@pytest.mark.parametrize("seed", [1, 2])
def test_anchoring_takes_the_shadow_out_and_sets_the_background_to_zero(seed: int) -> None:
    truth, stack = _smear(seed)
    true_rad = np.angle(truth)
    glass = np.abs(true_rad) < 1e-9
    own, anchored = _reconstruct(stack, "none"), _reconstruct(stack, "anchor")

    def error(estimate: acekf.FieldEstimate) -> np.ndarray:
        return np.angle(estimate.field * np.conj(truth))

    own_error, anchored_error = error(own), error(anchored)
    # Measured (seeds 1, 2): RMSE 0.142 -> 0.059 and 0.138 -> 0.058 rad (0.111 and 0.103
    # anchored to the texture's background alone); below 0.05 cycles/um 0.114 -> 0.026
    # and 0.106 -> 0.022.
    assert np.std(anchored_error) < 0.5 * np.std(own_error)
    assert _low_frequency_rmse(anchored_error) < 0.3 * _low_frequency_rmse(own_error)
    # Zero is the glass's phase: exactly on the glass the anchoring found, nearly on all of
    # it (measured -0.007 and -0.010 rad against the filter's own -0.137 and -0.138).
    found = background.anchor_to_background(
        own.field, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA
    ).background
    assert found.mean() == pytest.approx(anchored.background_share)
    assert abs(float(np.mean(anchored.phase_rad[found]))) < 1e-3
    assert abs(float(np.mean(anchored.phase_rad[glass]))) < 0.1 * abs(
        float(np.mean(own.phase_rad[glass]))
    )
    # The amplitude is the filter's own.
    np.testing.assert_allclose(anchored.amplitude, own.amplitude, rtol=0, atol=1e-5)


def test_the_mask_finds_glass_and_never_a_cell() -> None:
    truth, stack = _smear(1)
    field = _reconstruct(stack, "none").field
    glass = background.background_mask(field, PIXEL_UM)
    cells = np.abs(np.angle(truth)) > 1e-9
    assert glass.mean() > 0.2  # measured 0.30 of the image (the glass is 0.73, less fringes)
    assert not np.any(glass & cells)


def test_the_anchored_phase_finds_the_glass_up_to_the_cells_edges_and_never_a_cell() -> None:
    truth, stack = _smear(1)
    field = _reconstruct(stack, "none").field
    texture = background.background_mask(field, PIXEL_UM)
    anchored = background.anchor_to_background(field, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA)
    cells = np.abs(np.angle(truth)) > 1e-9
    # Measured 0.58 of the image against the texture's 0.30 (the glass is 0.73).
    assert anchored.background.mean() > texture.mean() + 0.15
    assert not np.any(anchored.background & cells)


def test_a_background_that_the_rest_lies_below_is_no_background() -> None:
    """Heights given with the wrong sign conjugate the field: the cells then lie below the
    glass, as the rest lies below a flat inside of cells taken for glass. Neither is
    anchored to; the zero is the phase of the mean."""
    _, stack = _smear(2)
    field = _reconstruct(stack, "none").field
    assert background.anchor_to_background(
        field, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA
    ).anchored
    mirrored = background.anchor_to_background(
        np.conj(field), Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA
    )
    assert background.background_mask(np.conj(field), PIXEL_UM).any()  # texture: glass
    assert not mirrored.anchored
    mean_phasor = np.mean(np.conj(field), dtype=np.complex128)
    np.testing.assert_allclose(
        mirrored.phase_rad, np.angle(np.conj(field) * np.conj(mean_phasor)), atol=1e-5
    )


def test_the_glass_found_again_reaches_the_cells_margin_where_the_phase_says_so() -> None:
    rng = np.random.default_rng(5)
    phase_rad = rng.normal(0.0, 0.01, (64, 64))
    phase_rad[:, 8:] += np.linspace(0.5, 1.0, 56)  # cells from column 8 on
    first = np.zeros(phase_rad.shape, dtype=bool)
    first[:, :4] = True  # the texture's glass, short of the cells
    # The phase's glass reaches the cells' margin, one 1 um pixel: columns 0-6.
    found = background.background_from_phase(phase_rad, first, PIXEL_UM)
    np.testing.assert_array_equal(found, np.broadcast_to(np.arange(64) < 7, found.shape))
    # Cells from column 4 would leave columns 0-2, under MIN_BACKGROUND: the first stays.
    phase_rad[:, 4:8] += 0.5
    np.testing.assert_array_equal(
        background.background_from_phase(phase_rad, first, PIXEL_UM), first
    )
    # Everything else below that glass: no cells above it, so no glass at all.
    assert not background.background_from_phase(-phase_rad, first, PIXEL_UM).any()
    # The rest as high as the glass, within its noise: the phase cannot say, the first
    # stays; and so does a first that is all or nothing.
    noise_rad = rng.normal(0.0, 0.01, phase_rad.shape)
    np.testing.assert_array_equal(
        background.background_from_phase(noise_rad, first, PIXEL_UM), first
    )
    for whole in (np.zeros_like(first), np.ones_like(first)):
        assert background.background_from_phase(phase_rad, whole, PIXEL_UM) is whole


def test_no_glass_no_mask_and_the_zero_at_the_mean() -> None:
    rng = np.random.default_rng(3)
    phase_rad = 0.3 * rng.normal(size=(64, 64)) + 2.5  # texture everywhere, far from zero
    field = np.exp(1j * phase_rad).astype(np.complex64)
    assert not background.background_mask(field, PIXEL_UM).any()
    anchored = background.anchor_to_background(field, Z_UM, WAVELENGTH_UM, PIXEL_UM)
    assert not anchored.anchored
    assert abs(float(np.mean(anchored.phase_rad))) < 0.01
    np.testing.assert_allclose(anchored.phase_rad, phase_rad - 2.5, atol=0.05)
    flat = np.ones((32, 32), dtype=np.complex64)
    assert not background.background_mask(flat, PIXEL_UM).any()


def test_a_texture_of_round_off_is_flat_not_an_error() -> None:
    # A prior far longer than a small image flattens its phase to 1e-19 rad, the texture's
    # power under float32's smallest normal: its floor used to underflow to 0, and log(0)
    # made Otsu's histogram fail ("autodetected range of [-inf, ...] is not finite").
    data = simulate.data_set_1(seed=2)
    stack = data.stack_counts[:10, :32, :32] * 1000.0 + 5.0
    options = acekf.AcekfOptions(prior_length_um=10_000.0)
    estimate = acekf.reconstruct(stack, data.z_um[:10], WAVELENGTH_UM, PIXEL_UM, options=options)
    assert estimate.background_share == 0.0
    assert float(np.ptp(estimate.phase_rad)) < 1e-6


def test_a_phase_offset_of_the_field_changes_nothing() -> None:
    _, stack = _smear(2)
    field = _reconstruct(stack, "none").field
    anchored = background.anchor_to_background(field, Z_UM, WAVELENGTH_UM, PIXEL_UM)
    turned = background.anchor_to_background(
        field * np.complex64(np.exp(3.0j)), Z_UM, WAVELENGTH_UM, PIXEL_UM
    )
    assert anchored.anchored
    np.testing.assert_array_equal(turned.background, anchored.background)
    np.testing.assert_allclose(turned.phase_rad, anchored.phase_rad, atol=1e-4)


@pytest.mark.parametrize("shape", [(64, 64), (45, 52)])
def test_the_small_grids_correction_is_the_normal_equations_solution(
    shape: tuple[int, int],
) -> None:
    """Against a dense solve of the same least squares on the full grid's band bins."""
    _, stack = _smear(1)
    field = _reconstruct(stack[:, : shape[0], : shape[1]], "none").field
    mask = background.background_mask(field, PIXEL_UM)
    phase_rad = np.angle(field).astype(np.float32)
    correction = background.low_frequency_correction(
        phase_rad, mask, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA
    )
    freq_sq = frequency_sq_per_um2(phase_rad.shape, PIXEL_UM)
    edge = background.band_edge_per_um(phase_rad.shape, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA)
    bins = np.argwhere(freq_sq < edge**2)
    size = phase_rad.size
    # B: the unitary inverse FFT's columns of the band's bins; B^H diag(M) B as a matrix.
    ny, nx = np.indices(phase_rad.shape)
    basis = np.exp(
        2j
        * np.pi
        * (
            np.outer(ny.ravel(), bins[:, 0]) / shape[0]
            + np.outer(nx.ravel(), bins[:, 1]) / shape[1]
        )
    ) / np.sqrt(size)
    weights = mask.ravel().astype(float)
    gram = basis.conj().T @ (weights[:, None] * basis)
    penalty = background.WEIGHT * phase_transfer_power(
        freq_sq[bins[:, 0], bins[:, 1]], Z_UM, WAVELENGTH_UM, CONDENSER_NA
    )
    theta = np.linalg.solve(
        gram + np.diag(penalty + background.RIDGE),
        -basis.conj().T @ (weights * phase_rad.ravel().astype(float)),
    )
    dense = (basis @ theta).real.reshape(phase_rad.shape)
    assert len(bins) > 20
    np.testing.assert_allclose(correction, dense, rtol=0, atol=5e-3)
    assert np.abs(dense).max() > 0.05  # a correction worth the name


def test_otsu_splits_two_populations_between_them() -> None:
    rng = np.random.default_rng(0)
    low, high = rng.normal(-4.0, 0.3, 600), rng.normal(1.0, 0.5, 400)
    threshold = background.otsu_threshold(np.concatenate([low, high]))
    assert low.max() < threshold < high.min()


def test_the_band_edge_is_where_the_stack_starts_to_see_the_phase() -> None:
    edge = background.band_edge_per_um((64, 64), Z_UM, WAVELENGTH_UM, PIXEL_UM)
    step = 1 / 64  # the image's finest frequency bin, cycles/um
    radius = np.arange(0.0, 0.75, step)
    peak = phase_transfer_power(radius**2, Z_UM, WAVELENGTH_UM).max()
    below, at = phase_transfer_power(np.array([edge - step, edge]) ** 2, Z_UM, WAVELENGTH_UM)
    assert phase_transfer_power(np.zeros(1), Z_UM, WAVELENGTH_UM)[0] == 0.0
    assert below < background.BAND_SHARE * peak <= at
    # Partial coherence damps the high frequencies, not the edge of the lowest.
    damped = background.band_edge_per_um((64, 64), Z_UM, WAVELENGTH_UM, PIXEL_UM, 0.05)
    assert 0.5 * edge < damped < 2 * edge


def test_a_bad_background_option_is_refused() -> None:
    with pytest.raises(ValueError, match="background must be 'anchor' or 'none'"):
        acekf.AcekfOptions(background="flat")  # type: ignore[arg-type]


def _recording_cg(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Patches the module's conjugate gradients to record (unknowns, iterations) per solve."""
    solves: list[tuple[int, int]] = []
    solve = background.cg

    def recorded(operator, rhs, **kwargs):  # type: ignore[no-untyped-def]
        iterations = [0]
        kwargs["callback"] = lambda _: iterations.__setitem__(0, iterations[0] + 1)
        result = solve(operator, rhs, **kwargs)
        solves.append((operator.shape[0], iterations[0]))
        return result

    monkeypatch.setattr(background, "cg", recorded)
    return solves


def test_a_tall_narrow_strip_s_band_is_capped_and_its_solve_bounded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 40000 x 2 strip once made a band as big as the image (20000 unknowns, CG to its
    1000-iteration cap: 20 s); now at most MAX_BAND_BINS unknowns, CG_MAX_ITERATIONS steps."""
    solves = _recording_cg(monkeypatch)
    rng = np.random.default_rng(0)
    phase_rad = rng.normal(0, 0.1, (40000, 2)).astype(np.float32)
    glass = np.zeros(phase_rad.shape, dtype=bool)
    glass[::3] = True
    correction = background.low_frequency_correction(phase_rad, glass, [-1.0, 1.0], 0.532, 0.5)
    (size, iterations), *_ = solves
    assert 0 < size <= background.MAX_BAND_BINS
    assert iterations <= background.CG_MAX_ITERATIONS
    assert correction.shape == phase_rad.shape and np.all(np.isfinite(correction))


def test_a_large_frame_s_band_is_capped(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 512 px frame over +-2 um at 0.5 um pixels once re-estimated ~50000 bins."""
    solves = _recording_cg(monkeypatch)
    phase_rad = np.zeros((512, 512), dtype=np.float32)
    glass = np.zeros(phase_rad.shape, dtype=bool)
    glass[:100] = True
    phase_rad[glass] = 0.3
    correction = background.low_frequency_correction(
        phase_rad, glass, np.linspace(-2, 2, 11), 0.532, 0.5
    )
    assert solves[0][0] <= background.MAX_BAND_BINS
    assert abs(float(np.mean(correction[glass])) + 0.3) < 0.05  # the glass is taken to zero


def test_an_unconverged_solve_is_kept_and_said(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Not silently: a warning; and kept, as every CG step from zero lowers the objective."""
    _, stack = _smear(1)
    field = _reconstruct(stack, "none").field
    mask = background.background_mask(field, PIXEL_UM)
    phase_rad = np.angle(field).astype(np.float32)

    def objective(correction: np.ndarray) -> float:  # its background part
        return float(np.sum((phase_rad[mask] + correction[mask]) ** 2))

    monkeypatch.setattr(background, "CG_MAX_ITERATIONS", 2)
    with caplog.at_level("WARNING", logger=background.__name__):
        partial = background.low_frequency_correction(
            phase_rad, mask, Z_UM, WAVELENGTH_UM, PIXEL_UM, CONDENSER_NA
        )
    assert "stopped unconverged after 2 iterations" in caplog.text
    assert np.abs(partial).max() > 0.01  # kept, not dropped
    assert objective(partial) < objective(np.zeros_like(partial))
