"""The phase maths: propagation, the sparse ACEKF and its input checks, on real arrays."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy import special

from focustrack_phase import acekf, baselines, simulate, transforms
from focustrack_phase.propagation import (
    FoldedGrid,
    coherence_envelope,
    frequency_sq_per_um2,
    propagate,
)

WAVELENGTH_UM = 0.532
PIXEL_UM = 1.0


def _weak_field(size_px: int = 64, scale: float = 0.2) -> np.ndarray:
    """The simulator's object with its departures from a plane wave scaled by `scale`."""
    field = simulate.weak_object(size_px, seed=3)
    return (1.0 + scale * (np.abs(field) - 1.0)) * np.exp(1j * scale * np.angle(field))


def _noiseless_stack(field: np.ndarray, z_um: np.ndarray, photons: float) -> np.ndarray:
    return np.stack(
        [photons * np.abs(propagate(field, float(z), WAVELENGTH_UM, PIXEL_UM)) ** 2 for z in z_um]
    )


def _phase_rmse(estimate: acekf.FieldEstimate, truth: np.ndarray) -> float:
    error = np.angle(estimate.field * np.conj(truth))
    return float(np.sqrt(np.mean((error - error.mean()) ** 2)))


def test_propagation_is_unitary_and_back_propagation_returns_the_field() -> None:
    field = simulate.weak_object(48, seed=1)
    ahead = propagate(field, 17.5, WAVELENGTH_UM, PIXEL_UM)
    assert np.sum(np.abs(ahead) ** 2) == pytest.approx(np.sum(np.abs(field) ** 2), rel=1e-12)
    assert not np.allclose(ahead, field, atol=1e-3)  # it did propagate
    np.testing.assert_allclose(propagate(ahead, -17.5, WAVELENGTH_UM, PIXEL_UM), field, atol=1e-12)


@pytest.mark.parametrize("shape", [(8, 8), (7, 10), (1, 5), (2, 3)])
def test_the_folded_grid_stands_for_the_full_one(shape: tuple[int, int]) -> None:
    grid = FoldedGrid(shape, 0.5)
    full_freq_sq = frequency_sq_per_um2(shape, 0.5)
    np.testing.assert_allclose(grid.expand(grid.freq_sq_per_um2), full_freq_sq, rtol=1e-12)
    quarter = np.random.default_rng(1).normal(size=grid.freq_sq_per_um2.shape) + 1j
    full = grid.expand(quarter)
    assert grid.mean(quarter.real) == pytest.approx(float(np.mean(full.real)), rel=1e-12)
    spectrum = np.random.default_rng(2).normal(size=shape) + 0j
    expected = spectrum * full
    grid.multiply(spectrum, quarter)
    np.testing.assert_allclose(spectrum, expected, rtol=1e-12)
    half = np.fft.rfft2(np.random.default_rng(3).normal(size=shape))
    expected_half = half * full[:, : half.shape[1]]
    grid.multiply(half, quarter)
    np.testing.assert_allclose(half, expected_half, rtol=1e-12)


def test_the_filter_leaves_the_stack_alone_and_a_zero_prior_length_is_the_white_prior() -> None:
    data = simulate.data_set_1(seed=3, gamma_photons=100.0, planes=20, size_px=32)
    before = data.stack_counts.copy()
    white = acekf.reconstruct(data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM)
    np.testing.assert_array_equal(data.stack_counts, before)
    zero = acekf.AcekfOptions(prior_length_um=0.0)
    again = acekf.reconstruct(data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM, options=zero)
    np.testing.assert_array_equal(again.field, white.field)
    smooth = acekf.AcekfOptions(prior_length_um=4.0)
    shaped = acekf.reconstruct(
        data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM, options=smooth
    )
    assert not np.allclose(shaped.field, white.field, atol=1e-4)
    assert acekf.prior_shape(np.array([0.0, 1.0]), 4.0)[0] == 1.0
    with pytest.raises(ValueError, match="prior_length_um"):
        acekf.AcekfOptions(prior_length_um=-1.0)


def test_a_smooth_prior_helps_on_a_smooth_object() -> None:
    data = simulate.data_set_1(4, 10.0, 50, 48, peak_phase_rad=0.3, smooth_um=2.0)

    def phase_rmse(options: acekf.AcekfOptions) -> float:
        estimate = acekf.reconstruct(
            data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM, options=options
        )
        return _phase_rmse(estimate, data.field)

    best_white = min(phase_rmse(acekf.AcekfOptions(q0=q0)) for q0 in (0.003, 0.01, 0.03))
    # Measured 0.050 against 0.072 rad (of a 0.087 rad spread).
    assert phase_rmse(acekf.AcekfOptions(q0=1.0, prior_length_um=2.0)) < 0.8 * best_white


@pytest.fixture(params=["opencv", "scipy"])
def fft_backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each test that takes it runs on OpenCV's DFT and on scipy.fft's."""
    if request.param == "scipy":
        monkeypatch.setattr(transforms, "OPENCV", None)
    elif transforms.OPENCV is None:
        pytest.skip("OpenCV is not installed")
    return str(request.param)


def test_an_opencv_that_does_not_import_leaves_scipy_fft(monkeypatch: pytest.MonkeyPatch) -> None:
    # None in sys.modules makes `import cv2` raise ImportError, as a wheel without its
    # system libraries (libGL) does.
    monkeypatch.setitem(sys.modules, "cv2", None)
    assert transforms._opencv() is None


# 5-smooth sizes (OpenCV's, when it is installed), odd ones, and a prime factor (scipy's).
TRANSFORM_SHAPES = [(16, 16), (9, 5), (6, 10), (3, 4), (2, 2), (7, 10), (45, 52)]


@pytest.mark.parametrize("shape", TRANSFORM_SHAPES)
def test_the_transforms_work_in_place_on_a_padded_image_and_leave_its_padding_zero(
    shape: tuple[int, int], fft_backend: str
) -> None:
    rng = np.random.default_rng(6)
    image = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)
    buffer = transforms.padded_zeros(shape, np.complex64)
    assert buffer.shape == (shape[0], shape[1] + transforms.ROW_PAD_PX)
    view = buffer[:, : shape[1]]
    view[...] = image
    assert transforms.dft2(view) is view
    np.testing.assert_allclose(view, np.fft.fft2(image), atol=2e-5 * image.size)
    assert transforms.idft2(view) is view  # unnormalised: N times the image
    np.testing.assert_allclose(view, image.size * image, atol=2e-5 * image.size)
    assert not buffer[:, shape[1] :].any()


@pytest.mark.parametrize("shape", TRANSFORM_SHAPES)
def test_a_real_image_filtered_by_a_kernel_of_the_frequency_s_modulus_is_the_full_product(
    shape: tuple[int, int], fft_backend: str
) -> None:
    rng = np.random.default_rng(7)
    grid = FoldedGrid(shape, 0.1)
    quarter_shape = grid.freq_sq_per_um2.shape
    kernel = (rng.normal(size=quarter_shape) + 1j * rng.normal(size=quarter_shape)).astype(
        np.complex64
    )
    weight = rng.normal(size=quarter_shape).astype(np.float32)
    image, added = rng.normal(size=(2, *shape)).astype(np.float32)
    expected = np.fft.ifft2(
        grid.expand(kernel) * (np.fft.fft2(image) + grid.expand(weight) * np.fft.fft2(added)),
        norm="forward",
    )
    real, imaginary, added_image = (transforms.padded_image(shape, np.float32) for _ in "abc")
    real[...], added_image[...] = image, added
    transforms.filter_real(real, imaginary, kernel, grid, (added_image, weight))
    assert np.abs(expected.imag).max() > 0.1 * np.abs(expected).max()  # a complex answer
    np.testing.assert_allclose(real + 1j * imaginary, expected, atol=1e-5 * np.abs(expected).max())
    assert not real.base[:, shape[1] :].any() and not imaginary.base[:, shape[1] :].any()


def _table_1_field(
    stack: np.ndarray, z_um: np.ndarray, pixel_um: float, options: acekf.AcekfOptions
) -> np.ndarray:
    """The filter written out plainly (eqs. 27-33, our update and noise, the coherence
    envelope) in double precision on the full grid, every product on a fresh array: the
    reference the fast filter's reorganisations must keep to."""
    gamma = float(np.mean(stack))
    freq_sq = frequency_sq_per_um2(stack.shape[1:], pixel_um)
    b = np.zeros(stack.shape[1:], dtype=np.complex128)
    b[0, 0] = np.sqrt(b.size)
    Q = np.full(b.shape, options.q0)
    P = np.full(b.shape, options.p0, dtype=np.complex128)
    z_prev = 0.0
    for k in acekf.plane_order(z_um):
        H = np.exp(-1j * np.pi * WAVELENGTH_UM * (z_um[k] - z_prev) * freq_sq)  # eq. 3
        z_prev = z_um[k]
        b, P = H * b, H * P * H  # eqs. 27, 29
        envelope = coherence_envelope(freq_sq, z_um[k], options.condenser_na)
        E = np.ones_like(freq_sq) if envelope is None else envelope.astype(np.float64)
        S = Q + P
        inverse = 1 / (2 * E**2 * S.real + 1 / gamma + np.mean(Q) ** 2)
        Q, P = Q - E**2 * np.abs(S) ** 2 * inverse, P - E**2 * S**2 * inverse  # eqs. 31-32
        Q = np.maximum(Q, np.abs(P))
        gain = E * S * inverse
        a_hat = np.fft.ifft2(b, norm="ortho")  # eq. 30
        modulus = np.abs(a_hat)
        floored = np.maximum(modulus, options.amplitude_floor)
        residual = stack[k] / gamma - modulus**2
        excess = modulus**2 - 1
        if options.update == "paper":  # eq. 33: the residual over a_hat^*
            turned = a_hat / (modulus * floored)
            innovation = np.fft.fft2(turned * residual, norm="ortho")
            innovation += (1 - E) * np.fft.fft2(turned * excess, norm="ortho")
            b = b + gain * innovation
        else:  # ours: the gain on the real residual, then the turn e^{i theta}
            spectrum = np.fft.fft2(residual / floored, norm="ortho")
            spectrum += (1 - E) * np.fft.fft2(excess / floored, norm="ortho")
            correction = np.fft.ifft2(gain * spectrum, norm="ortho")
            b = b + np.fft.fft2(correction * a_hat / modulus, norm="ortho")
    return np.fft.ifft2(np.exp(1j * np.pi * WAVELENGTH_UM * z_prev * freq_sq) * b, norm="ortho")


@pytest.mark.parametrize("update", ["phase_frame", "paper"])
@pytest.mark.parametrize("condenser_na", [0.0, 0.3])
@pytest.mark.parametrize("shape", [(32, 32), (27, 34)])
def test_the_fast_filter_is_the_plain_one_to_single_precision(
    update: acekf.Update, condenser_na: float, shape: tuple[int, int], fft_backend: str
) -> None:
    truth = simulate.weak_object(max(shape), seed=6, peak_phase_rad=1.5)[: shape[0], : shape[1]]
    # Both sides of focus, out of order, a repeated height and the focal plane itself.
    z_um = np.array([3.0, -1.5, 0.0, 1.5, 1.5, -3.0, 4.5])
    pixel_um = 0.2
    clean = np.stack(
        [np.abs(propagate(truth, float(z), WAVELENGTH_UM, pixel_um)) ** 2 for z in z_um]
    )
    stack = np.random.default_rng(6).poisson(300.0 * clean).astype(np.float32)
    options = acekf.AcekfOptions(
        q0=0.03, p0=-0.01, update=update, condenser_na=condenser_na, background="none"
    )
    fast = acekf.reconstruct(stack, z_um, WAVELENGTH_UM, pixel_um, options=options).field
    plain = _table_1_field(stack.astype(np.float64), z_um, pixel_um, options)
    assert fast.dtype == np.complex64
    assert not np.allclose(plain, 1.0, atol=0.05)  # the planes did move the field
    # Measured within 6e-6 of the double-precision filter (single precision's round-off).
    np.testing.assert_allclose(fast, plain, rtol=0, atol=2e-5)


def test_a_prior_that_knows_the_object_s_spectra_replaces_q0_and_p0() -> None:
    data = simulate.data_set_1(seed=3, gamma_photons=10.0, planes=30, size_px=32)
    freq_sq = FoldedGrid((32, 32), PIXEL_UM).freq_sq_per_um2
    white = acekf.AcekfOptions(q0=0.3, p0=-0.1)
    q0, p0 = acekf.initial_covariances(white, freq_sq)
    assert np.all(q0 == np.float32(0.3)) and np.all(p0 == np.complex64(-0.1))
    given = acekf.initial_covariances(white, freq_sq, (np.full(freq_sq.shape, 2.0), -q0))
    np.testing.assert_array_equal(given[0], 2.0)
    np.testing.assert_array_equal(given[1], -q0)
    same = acekf.reconstruct(
        data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM, options=white, prior=(q0, p0)
    )
    plain = acekf.reconstruct(data.stack_counts, data.z_um, WAVELENGTH_UM, PIXEL_UM, options=white)
    np.testing.assert_array_equal(same.field, plain.field)
    for prior, message in (
        ((q0[:-1], p0[:-1]), "folded grid's shape"),
        ((q0, 2 * q0), "Q_0 >= |P_0|"),
        ((q0 + 0j, p0), "real"),
        ((np.full_like(q0, np.nan), p0), "finite"),
    ):
        with pytest.raises(ValueError, match=message):
            acekf.initial_covariances(white, freq_sq, prior)


def test_the_filter_recovers_a_known_weak_phase_from_a_noiseless_stack() -> None:
    truth = _weak_field()
    z_um = np.arange(1, 41) * 1.0
    stack = _noiseless_stack(truth, z_um, 1e4)
    estimate = acekf.reconstruct(stack, z_um, WAVELENGTH_UM, PIXEL_UM)
    flat = float(np.std(np.angle(truth)))
    # 0.016 of 0.028 rad measured: the lowest frequencies stay invisible within 40 um.
    assert _phase_rmse(estimate, truth) < 0.6 * flat
    assert estimate.gamma_photons == pytest.approx(np.mean(stack), rel=1e-12)
    relative_intensity = np.abs(truth) ** 2 / np.mean(np.abs(truth) ** 2)
    assert np.sqrt(np.mean((estimate.intensity - relative_intensity) ** 2)) < 0.01


def test_shuffled_planes_give_the_same_field_and_both_sides_of_focus_work() -> None:
    truth = _weak_field()
    z_um = np.concatenate([-np.arange(1, 21) * 1.0, np.arange(1, 21) * 1.0])
    stack = _noiseless_stack(truth, z_um, 1e4)
    estimate = acekf.reconstruct(stack, z_um, WAVELENGTH_UM, PIXEL_UM)
    order = np.random.default_rng(7).permutation(len(z_um))
    shuffled = acekf.reconstruct(stack[order], z_um[order], WAVELENGTH_UM, PIXEL_UM)
    np.testing.assert_allclose(shuffled.field, estimate.field, atol=1e-12)
    assert _phase_rmse(estimate, truth) < 0.6 * float(np.std(np.angle(truth)))


def test_the_paper_s_data_set_1_has_its_photon_count_and_planes() -> None:
    data = simulate.data_set_1(seed=2)
    assert data.stack_counts.shape == (100, 100, 100)
    np.testing.assert_allclose(data.z_um, np.arange(1, 101) * 0.5)
    assert np.mean(np.abs(data.field) ** 2) == pytest.approx(1.0)
    assert np.mean(data.stack_counts) == pytest.approx(0.998, abs=0.01)
    assert np.ptp(np.angle(data.field)) < 1.0


@pytest.mark.parametrize(
    ("stack", "z_um", "message"),
    [
        (np.ones((4, 8)), [1.0] * 4, "3-D array"),
        (np.ones((3, 8, 8)), [1.0, 2.0], "one height per frame"),
        (np.ones((2, 8, 8)), [1.0, np.nan], "finite"),
        (np.ones((2, 8, 8)), [1.0, 10**400], "flat list of finite numbers"),  # past float64
        (np.ones((2, 8, 8)), [1.0, [2.0, 3.0]], "flat list of finite numbers"),  # ragged
        (np.zeros((2, 8, 8)), [1.0, 2.0], "frame 0 has a mean of 0 counts"),
        (np.stack([np.ones((8, 8)), -np.ones((8, 8))]), [1.0, 2.0], "frame 1 has a mean of -1"),
        (np.full((2, 8, 8), np.inf), [1.0, 2.0], "finite"),
        (np.full((2, 8, 8), np.nan), [1.0, 2.0], "finite"),
        (np.full((2, 8, 8), 1e308), [1.0, 2.0], "overflows"),
    ],
)
def test_bad_inputs_raise_a_clear_value_error(
    stack: np.ndarray, z_um: list[float], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        acekf.reconstruct(stack, z_um, WAVELENGTH_UM, PIXEL_UM)
    with pytest.raises(ValueError, match=message):
        baselines.weak_object_least_squares(stack, z_um, WAVELENGTH_UM, PIXEL_UM)


def test_bad_optics_and_options_raise_a_clear_value_error() -> None:
    stack = np.ones((2, 8, 8))
    with pytest.raises(ValueError, match="wavelength_um"):
        acekf.reconstruct(stack, [1.0, 2.0], 0.0, PIXEL_UM)
    with pytest.raises(ValueError, match="photons_per_count"):
        acekf.reconstruct(stack, [1.0, 2.0], WAVELENGTH_UM, PIXEL_UM, photons_per_count=-1.0)
    with pytest.raises(ValueError, match="p0"):
        acekf.AcekfOptions(q0=0.01, p0=0.1)
    with pytest.raises(ValueError, match="two planes"):
        baselines.tie_tikhonov(stack, [1.0, 1.0], WAVELENGTH_UM, PIXEL_UM)


def test_the_weak_object_baselines_recover_the_noiseless_phase() -> None:
    truth = _weak_field()
    z_um = np.arange(1, 41) * 1.0
    stack = _noiseless_stack(truth, z_um, 1e4)
    flat = float(np.std(np.angle(truth)))
    wols = baselines.weak_object_least_squares(stack, z_um, WAVELENGTH_UM, PIXEL_UM, alpha=1e-3)
    assert _phase_rmse(wols, truth) < 0.35 * flat
    tie = baselines.tie_tikhonov(stack, z_um, WAVELENGTH_UM, PIXEL_UM, alpha=1e-3)
    assert _phase_rmse(tie, truth) < flat


def test_the_phase_frame_update_holds_where_eq_33_drifts_on_a_stronger_phase() -> None:
    truth = simulate.weak_object(64, seed=5, peak_phase_rad=1.0)
    z_um = np.arange(1, 41) * 1.0
    stack = _noiseless_stack(truth, z_um, 1e3)
    ours = acekf.reconstruct(stack, z_um, WAVELENGTH_UM, PIXEL_UM)
    paper = acekf.reconstruct(
        stack, z_um, WAVELENGTH_UM, PIXEL_UM, options=acekf.AcekfOptions(update="paper")
    )
    # Eq. 33 divides by a_hat^*, whose phase reaches 1 rad here: its diagonal gain then
    # mixes f and -f wrongly. Measured 0.12 against 0.21 rad (of a 0.37 rad spread).
    assert _phase_rmse(ours, truth) < 0.7 * _phase_rmse(paper, truth)
    assert _phase_rmse(ours, truth) < 0.4 * float(np.std(np.angle(truth)))


def test_the_coherence_envelope_is_a_jinc_of_defocus_and_frequency() -> None:
    freq_sq = np.array([[0.0, 0.01], [0.04, 0.09]])
    assert coherence_envelope(freq_sq, 10.0, 0.0) is None  # coherent: no damping
    envelope = coherence_envelope(freq_sq, -10.0, 0.1)
    assert envelope is not None
    v = 2 * np.pi * 10.0 * 0.1 * np.sqrt(freq_sq)
    expected = np.where(v > 0, 2 * special.j1(v) / np.where(v > 0, v, 1.0), 1.0)
    np.testing.assert_allclose(envelope, expected, rtol=1e-6)
    assert envelope[0, 0] == 1.0 and envelope[1, 1] < envelope[0, 1] < 1.0


def test_modelling_partial_coherence_recovers_what_the_coherent_model_misses() -> None:
    truth = simulate.weak_object(48, seed=2)
    z_um = np.arange(1, 21) * 2.5
    condenser_na = 0.05
    stack = simulate.partially_coherent_stack(
        truth, z_um, WAVELENGTH_UM, PIXEL_UM, 1e3, condenser_na, seed=2
    )
    assert len(simulate.source_points_per_um(condenser_na, WAVELENGTH_UM, (48, 48), 1.0)) > 20
    # The filter's own fields: anchoring to the background would hide part of what the
    # envelope is for (the coherent model's shadow).
    coherent = acekf.reconstruct(
        stack, z_um, WAVELENGTH_UM, PIXEL_UM, options=acekf.AcekfOptions(background="none")
    )
    modelled = acekf.reconstruct(
        stack,
        z_um,
        WAVELENGTH_UM,
        PIXEL_UM,
        options=acekf.AcekfOptions(condenser_na=condenser_na, background="none"),
    )
    # Measured 0.033 against 0.072 rad.
    assert _phase_rmse(modelled, truth) < 0.7 * _phase_rmse(coherent, truth)


def test_a_point_source_is_coherent_light() -> None:
    truth = simulate.weak_object(32, seed=4)
    z_um = np.array([5.0, 10.0])
    points = simulate.source_points_per_um(0.0, WAVELENGTH_UM, (32, 32), PIXEL_UM)
    np.testing.assert_array_equal(points, [[0.0, 0.0]])
    partial = simulate.partially_coherent_stack(truth, z_um, WAVELENGTH_UM, PIXEL_UM, 1e4, 0.0, 9)
    coherent = simulate.through_focus_stack(truth, z_um, WAVELENGTH_UM, PIXEL_UM, 1e4, 9)
    np.testing.assert_array_equal(partial, coherent)


def test_tie_fits_its_slope_over_the_window_of_planes_it_is_given() -> None:
    truth = _weak_field(scale=0.5)
    z_um = np.arange(1, 41) * 0.25
    clean = _noiseless_stack(truth, z_um, 1e4)
    noisy = np.random.default_rng(3).poisson(clean / 100.0).astype(np.float64)  # 100 photons
    nearest = baselines.tie_tikhonov(noisy, z_um, WAVELENGTH_UM, PIXEL_UM, alpha=1e-2)
    window = baselines.tie_tikhonov(noisy, z_um, WAVELENGTH_UM, PIXEL_UM, alpha=1e-2, max_dz_um=5.0)
    # Twenty planes average the shot noise that two planes 0.25 um apart amplify.
    assert _phase_rmse(window, truth) < 0.5 * _phase_rmse(nearest, truth)


def test_a_run_away_filter_says_so_instead_of_answering_noise() -> None:
    data = simulate.data_set_1(seed=2, gamma_photons=1e4, size_px=32)
    wide = acekf.AcekfOptions(q0=3.0, p0=-2.7)  # a prior far wider than a 0.5 rad object
    with pytest.raises(acekf.FilterDivergedError, match="a smaller prior"):
        acekf.reconstruct(
            data.stack_counts, data.z_um, data.wavelength_um, data.pixel_um, options=wide
        )
    assert issubclass(acekf.FilterDivergedError, ValueError)  # a 422 on REST
    stable = acekf.reconstruct(data.stack_counts, data.z_um, data.wavelength_um, data.pixel_um)
    assert _phase_rmse(stable, data.field) < 0.5 * float(np.std(np.angle(data.field)))


def test_q0_is_bounded_where_the_prior_would_flatten_the_phase() -> None:
    """q0 of 1e3 (once allowed, up to 1e6) swamped the gain, and 5e-324 held the field to
    the plane wave: a flat phase and a 200 either way."""
    from focustrack.bench.phase import FILTER_Q0

    assert acekf.MIN_Q0 <= min(FILTER_Q0) <= max(FILTER_Q0) <= acekf.MAX_Q0  # the bench's grid
    acekf.AcekfOptions(q0=acekf.MAX_Q0)
    acekf.AcekfOptions(q0=acekf.MIN_Q0)
    for q0 in (1e3, 5e-324, 1e-9):
        with pytest.raises(ValueError, match=r"q0 must be in \[1e-08, 10\]"):
            acekf.AcekfOptions(q0=q0)


@pytest.mark.parametrize(
    ("setting", "value"),
    [("amplitude_floor", np.inf), ("amplitude_floor", 1.5), ("prior_length_um", np.inf)],
)
def test_settings_past_their_bounds_are_refused(setting: str, value: float) -> None:
    """An amplitude floor of inf clipped every pixel: a flat phase and a 200."""
    with pytest.raises(ValueError, match=f"{setting} must be in"):
        acekf.AcekfOptions(**{setting: value})


@pytest.mark.parametrize(
    ("counts", "photons_per_count"), [(1e-300, 1.0), (1000.0, 1e-30), (1e-4, 1.0)]
)
def test_a_stack_of_almost_no_photons_is_refused_naming_the_gain(
    counts: float, photons_per_count: float
) -> None:
    """Once a flat phase or a 'smaller prior' 422 that sent the user the wrong way."""
    rng = np.random.default_rng(0)
    stack = counts * (1 + 0.1 * rng.random((2, 8, 8)))
    with pytest.raises(ValueError, match=r"check photons_per_count \(the camera's gain\)"):
        acekf.reconstruct(stack, [1.0, 2.0], WAVELENGTH_UM, PIXEL_UM, photons_per_count)


def test_the_paper_s_photon_count_is_above_the_floor() -> None:
    assert acekf.MIN_GAMMA_PHOTONS < 0.998 / 10  # the bench's sparsest, with room
    stack = np.random.default_rng(0).poisson(0.998, (2, 16, 16)).astype(float)
    _, gamma = acekf.validate_stack(stack, [1.0, 2.0], WAVELENGTH_UM, PIXEL_UM, 1.0)
    assert gamma > acekf.MIN_GAMMA_PHOTONS
