"""Best focus from a curve: sub-step accuracy, flags, validation, and an honest sigma."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import (
    MAX_ABS_Z_UM,
    MAX_PRIOR_SIGMA_UM,
    MIN_PRIOR_SIGMA_UM,
    FocusFlag,
    Prior,
)
from focustrack_focus.peak import PeakMode, PeakSettings, find_peak

Z_UM = np.arange(-3.0, 3.01, 0.5)


def gaussian(z_um: np.ndarray, centre_um: float, width_um: float = 0.8) -> np.ndarray:
    return 1.0 + 5.0 * np.exp(-0.5 * ((z_um - centre_um) / width_um) ** 2)


@pytest.mark.parametrize("centre_um", [-0.37, 0.0, 0.21, 1.4])
def test_sub_step_peak_of_a_clean_curve(centre_um: float) -> None:
    fit = find_peak(Z_UM, gaussian(Z_UM, centre_um))
    assert fit.flags == frozenset()
    assert fit.z_um == pytest.approx(centre_um, abs=0.05)  # a tenth of the 0.5 um step
    assert 0 < fit.sigma_um < 0.125  # a quarter step


def test_unsorted_input_gives_the_same_answer() -> None:
    order = np.random.default_rng(0).permutation(Z_UM.size)
    a = find_peak(Z_UM, gaussian(Z_UM, 0.3))
    b = find_peak(Z_UM[order], gaussian(Z_UM, 0.3)[order])
    assert a == b


@pytest.mark.parametrize(
    ("centre_um", "flag", "z_um"),
    [(-4.0, FocusFlag.EDGE_LOW, -3.0), (5.0, FocusFlag.EDGE_HIGH, 3.0)],
)
def test_edge_peaks_say_which_way_to_extend(centre_um: float, flag: FocusFlag, z_um: float) -> None:
    fit = find_peak(Z_UM, gaussian(Z_UM, centre_um))
    assert flag in fit.flags and fit.z_um == z_um and fit.sigma_um is None
    assert not fit.is_observation


def test_flat_curves_are_no_measurement() -> None:
    rng = np.random.default_rng(1)
    for scores in (np.full(Z_UM.size, 2.0), 2.0 + 0.01 * rng.normal(size=Z_UM.size)):
        fit = find_peak(Z_UM, scores)
        assert fit.flags == {FocusFlag.FLAT} and fit.z_um is None and fit.sigma_um is None


def test_two_peaks_are_flagged_with_the_runner_up_not_a_wide_sigma() -> None:
    z = np.arange(-5.0, 5.01, 0.5)
    single = find_peak(z, gaussian(z, -2.0))
    # half as prominent: probability 1 / (1 + 0.5**2) = 0.8, clear enough (not ambiguous)
    double = find_peak(z, gaussian(z, -2.0) + 0.5 * (gaussian(z, 2.5) - 1.0))
    assert double.flags == {FocusFlag.MULTI_PEAK}
    assert double.z_um == pytest.approx(-2.0, abs=0.1)
    assert double.runner_up_z_um == 2.5
    assert 0.75 < double.chosen_probability < 1.0
    # the choice is said by the flag and the probability, not by a sigma of the peaks' spread
    # (which was 2.2 um here): a fifth of the 0.5 um step
    assert double.sigma_um < 0.1
    assert single.runner_up_z_um is None and single.chosen_probability == 1.0


def test_two_equal_peaks_are_ambiguous_and_a_prior_decides() -> None:
    z = np.arange(-5.0, 5.01, 0.5)
    scores = gaussian(z, -2.0) + 0.95 * (gaussian(z, 2.5) - 1.0)
    fit = find_peak(z, scores)
    assert {FocusFlag.MULTI_PEAK, FocusFlag.AMBIGUOUS} <= fit.flags
    assert 0.5 <= fit.chosen_probability < 0.75
    informed = find_peak(z, scores, prior=Prior(2.0, 1.0))
    assert informed.z_um == pytest.approx(2.5, abs=0.1)
    assert informed.runner_up_z_um == -2.0
    assert FocusFlag.AMBIGUOUS not in informed.flags


def test_posterior_is_the_product_of_prior_and_measurement() -> None:
    fit = find_peak(Z_UM, gaussian(Z_UM, 0.3))
    assert fit.sigma_um is not None
    z, sigma = fit.posterior(Prior(1.0, fit.sigma_um))  # equal weights: halfway
    assert z == pytest.approx((fit.z_um + 1.0) / 2) and sigma == pytest.approx(
        fit.sigma_um / np.sqrt(2)
    )
    edge = find_peak(Z_UM, gaussian(Z_UM, 5.0))
    assert edge.posterior(Prior(1.0, 1.0)) is None
    with pytest.raises(ValueError, match="sigma_um must be within"):
        Prior(0.0, 0.0)


@pytest.mark.parametrize(
    ("z_um", "sigma_um", "field"),
    [
        (2.0, 1e-200, "sigma_um"),
        (2.0, 1e200, "sigma_um"),
        (1e300, 1.0, "z_um"),
        (np.nan, 1, "z_um"),
    ],
)
def test_a_prior_the_maths_cannot_compute_is_refused(z_um: float, sigma_um: float, field: str):
    with pytest.raises(ValueError, match=f"prior's {field}"):
        Prior(z_um, sigma_um)


@pytest.mark.parametrize(
    "prior",
    [
        Prior(MAX_ABS_Z_UM, MIN_PRIOR_SIGMA_UM),
        Prior(-MAX_ABS_Z_UM, MAX_PRIOR_SIGMA_UM),
        Prior(0.3, MIN_PRIOR_SIGMA_UM),
    ],
)
def test_a_prior_at_its_bounds_gives_a_finite_posterior(prior: Prior) -> None:
    fit = find_peak(Z_UM, gaussian(Z_UM, 0.3), prior=prior)
    assert fit.z_um == pytest.approx(0.3, abs=0.05)
    posterior = fit.posterior(prior)
    assert posterior is not None and all(np.isfinite(posterior)) and posterior[1] > 0
    # the posterior lies between the prior and the measurement
    assert min(fit.z_um, prior.z_um) <= posterior[0] <= max(fit.z_um, prior.z_um)


def test_an_interior_peak_beside_a_rising_end_is_measured_and_flagged() -> None:
    # a sharp peak, then the curve climbs to the last frame (a background or another peak)
    z = np.arange(0.0, 10.01, 0.5)
    scores = gaussian(z, 3.0) + 4.0 * np.exp((z - 10.0) / 1.5)
    fit = find_peak(z, scores)
    assert fit.z_um == pytest.approx(3.0, abs=0.1) and fit.sigma_um is not None
    assert FocusFlag.MULTI_PEAK in fit.flags
    assert fit.runner_up_z_um == 10.0


def test_a_one_frame_spike_on_a_slope_is_not_a_peak() -> None:
    # dense sampling (0.25 um): no real peak is one frame wide; the focus lies above
    z = np.arange(0.0, 2.01, 0.25)
    scores = 1.0 + 0.1 * z
    scores[4] += 0.3
    fit = find_peak(z, scores)
    assert FocusFlag.EDGE_HIGH in fit.flags and fit.sigma_um is None


@pytest.mark.parametrize("baseline", [0.0, 2.0])
@pytest.mark.parametrize("mode", list(PeakMode))
def test_a_curve_flat_but_for_a_one_frame_spike_is_flat(baseline: float, mode: PeakMode) -> None:
    """Despiked, the curve was all baseline, and its first frame was read as an edge."""
    z = np.arange(-5.0, 5.01, 0.5)
    scores = np.full(z.size, baseline)
    scores[10] += 1.0 if mode is PeakMode.MAX else -1.0
    fit = find_peak(z, scores, PeakSettings(mode=mode))
    assert fit.flags == {FocusFlag.FLAT} and fit.z_um is None


def test_a_spike_far_above_a_faint_peak_leaves_the_peak_read() -> None:
    """Once the spike is gone, the contrast is judged against the other frames' maximum,
    not against the spike's (which made this short curve's 3 % contrast flat)."""
    z = np.arange(5) * 0.5
    scores = 1.0 + 0.03 * np.exp(-0.5 * ((z - 1.0) / 0.8) ** 2)
    scores[3] += 10.0
    fit = find_peak(z, scores)
    assert fit.flags == frozenset() and fit.z_um == pytest.approx(1.0, abs=0.05)


def test_a_narrow_peak_sampled_coarsely_is_a_peak_not_flat() -> None:
    # 3 um apart, a real peak shows in one frame only above a plateau with a little noise
    z = np.arange(0.0, 30.01, 3.0)
    scores = 1.0 + 0.002 * np.random.default_rng(3).normal(size=z.size)
    scores[5] += 0.4
    fit = find_peak(z, scores)
    assert fit.is_observation and fit.z_um == pytest.approx(15.0, abs=1.5)
    assert FocusFlag.FLAT not in fit.flags


def test_valley_mode_finds_the_contrast_minimum() -> None:
    z = np.arange(0.0, 10.01, 0.3)
    scores = 3.0 - gaussian(z, 5.05, 0.6) / 3.0  # a dip between two shoulders
    assert find_peak(z, scores, PeakSettings(mode=PeakMode.VALLEY)).z_um == pytest.approx(
        5.05, abs=0.05
    )
    assert find_peak(z, scores).z_um != pytest.approx(5.05, abs=1.0)


@pytest.mark.parametrize(
    ("z_um", "scores", "message"),
    [
        ([0, 1, 2], [1, 2], "3 z values but 2 scores"),
        ([0, 1], [1, 2], "at least 3 frames"),
        ([0, 1, np.nan], [1, 2, 1], "z values must be finite"),
        ([0, 1, 2], [1, np.inf, 1], "scores must be finite"),
        ([0, 1, 1], [1, 2, 1], "distinct"),
        ([1e-300, 2e-300, 3e-300], [1, 2, 1], "at least 1e-06 um apart"),
    ],
)
def test_bad_curves_are_refused_with_the_reason(z_um, scores, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        find_peak(np.array(z_um, float), np.array(scores, float))


@pytest.mark.parametrize("origin_um", [0.0, MAX_ABS_Z_UM - 1.0])
def test_a_peak_sampled_every_picometre_is_read(origin_um: float) -> None:
    """The finest step allowed, rounded as floats round it, even 1e6 um away."""
    step_um = 1e-6
    z = origin_um + np.arange(-10, 11) * step_um
    fit = find_peak(z, gaussian(z, float(z[10]) + 0.3 * step_um, 3 * step_um))
    assert fit.flags == frozenset() and fit.z_um is not None
    assert (fit.z_um - z[10]) / step_um == pytest.approx(0.3, abs=0.05)


@pytest.mark.parametrize("slope_per_um", [-0.4, 0.25, 0.5])
def test_a_sloping_background_widens_sigma_to_cover_the_shift(slope_per_um: float) -> None:
    """A broad peak times exp(c z) (dust on another plane adds contrast towards it) peaks
    c w**2 away from its centre; sigma grows to cover that shift."""
    z = np.arange(-3.0, 3.01, 0.5)
    width_um = 0.8
    symmetric = find_peak(z, gaussian(z, 0.0, width_um))
    lopsided = find_peak(z, gaussian(z, 0.0, width_um) * np.exp(slope_per_um * z))
    assert abs(lopsided.z_um) > 0.1  # the shift is real ...
    assert abs(lopsided.z_um) <= 3.0 * lopsided.sigma_um  # ... and inside three sigmas
    assert lopsided.sigma_um > 2.0 * symmetric.sigma_um


def test_noise_widens_the_fit_window_and_sigma() -> None:
    """On a noisy curve more frames are fitted; the error stays within three sigmas."""
    z = np.arange(-3.0, 3.01, 0.25)
    rng = np.random.default_rng(3)
    zscores = []
    for _ in range(200):
        truth = float(rng.uniform(-0.5, 0.5))
        scores = gaussian(z, truth, 1.0) + rng.normal(0.0, 0.05, z.size)
        fit = find_peak(z, scores)
        zscores.append((fit.z_um - truth) / fit.sigma_um)
    assert 0.6 < np.std(zscores) < 1.5, np.std(zscores)


def test_a_window_above_focus_with_a_rising_background_names_both_ways() -> None:
    # focus at 0; the window 4..12 um sees its faint tail at the low end and a background
    # rising to the high end: both ends are candidates, and a prior decides between them
    z = np.arange(4.0, 12.01, 1.0)
    scores = 1 + 5 * np.exp(-0.5 * (z / 1.5) ** 2) + np.exp((z - 12) / 2.0)
    blind = find_peak(z, scores)
    assert FocusFlag.MULTI_PEAK in blind.flags and blind.runner_up_z_um == 4.0
    informed = find_peak(z, scores, prior=Prior(1.0, 3.0))
    assert FocusFlag.EDGE_LOW in informed.flags and informed.z_um == 4.0
    assert informed.runner_up_z_um == 12.0


def faint_bump(seed: int, height: float) -> tuple[np.ndarray, np.ndarray]:
    """100 frames 0.5 um apart: a 19 um wide bump of `height` noise sigmas at z = 25 um on a
    level of 1000 sigmas (a metric all but blind to the specimen, VOLLATH_F4 on the WSI
    microscope), plus unit white noise."""
    z = 0.5 * np.arange(100)
    noise = np.random.default_rng(seed).normal(size=z.size)
    return z, 1000.0 + height * np.exp(-0.5 * ((z - 25.0) / 19.0) ** 2) + noise


@pytest.mark.parametrize("seed", range(8))
def test_a_faint_bump_drowned_in_noise_is_flagged_not_a_confident_pick(seed: int) -> None:
    z, scores = faint_bump(seed, height=20.0)
    fit = find_peak(z, scores)
    # frames several um from the noise-picked best one are as likely the top: said by the
    # flag and the probability, and by a sigma of the top's spread, which covers the miss
    assert FocusFlag.AMBIGUOUS in fit.flags
    assert fit.chosen_probability < 0.6
    assert fit.sigma_um > 2.0  # four steps
    assert abs(fit.z_um - 25.0) <= 2.0 * fit.sigma_um


def test_a_clear_peak_in_the_same_noise_keeps_a_small_sigma() -> None:
    z, scores = faint_bump(0, height=0.0)
    scores = scores + 200.0 * np.exp(-0.5 * ((z - 25.0) / 1.75) ** 2)  # Brenner-like
    fit = find_peak(z, scores)
    assert fit.flags == frozenset() and fit.chosen_probability == 1.0
    assert fit.z_um == pytest.approx(25.0, abs=0.125)
    assert fit.sigma_um < 0.125


@pytest.mark.parametrize("seed", [1, 2, 4, 5])
def test_a_known_noise_floor_makes_a_short_window_of_noise_flat(seed: int) -> None:
    """Seven frames cannot tell their noise from a peak's shape: alone they read a peak;
    with the metric's known noise (0.8 % of its level) they are flat."""
    z = 0.5 * np.arange(7)
    scores = 1000.0 + 8.0 * np.random.default_rng(seed).normal(size=z.size)
    assert find_peak(z, scores).z_um is not None
    known = find_peak(z, scores, PeakSettings(min_relative_noise=0.008))
    assert known.flags == {FocusFlag.FLAT} and known.z_um is None


def test_a_noise_floor_of_the_maximum_turns_a_metric_off() -> None:
    """1 (noise as large as the curve's maximum) is how an unusable metric is turned off:
    even a clear peak (or a bare end rise) reads flat, while 0.1 still measures it."""
    for scores in (gaussian(Z_UM, 0.3), 1.0 + np.exp(Z_UM)):
        off = find_peak(Z_UM, scores, PeakSettings(min_relative_noise=1.0))
        assert off.flags == {FocusFlag.FLAT} and off.z_um is None and off.sigma_um is None
    assert find_peak(Z_UM, gaussian(Z_UM, 0.3), PeakSettings(min_relative_noise=0.01)).z_um


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        # lab code built these directly, unchecked: a sigma whose square overflows
        ({"systematic_sigma_um": 1e308}, r"systematic_sigma_um must be a number in \[0, 1000\]"),
        ({"systematic_sigma_um": -0.1}, "systematic_sigma_um"),
        ({"min_snr": float("inf")}, "min_snr must be a finite number >= 0"),
        ({"min_relative_noise": float("nan")}, "min_relative_noise"),
        ({"curve_fwhm_um": 0.0}, "curve_fwhm_um must be a finite number > 0"),
        ({"max_reach": 0}, "max_reach must be a whole number >= 1"),
        ({"broad_top_exempt_frames": 2.5}, "broad_top_exempt_frames"),
        ({"mode": "top"}, "mode must be one of 'max', 'valley'"),
        ({"ambiguous_below": True}, "ambiguous_below"),
    ],
)
def test_settings_out_of_range_are_refused_naming_them(settings: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PeakSettings(**settings)


def test_a_mode_given_as_its_name_is_the_mode() -> None:
    assert PeakSettings(mode="valley").mode is PeakMode.VALLEY  # type: ignore[arg-type]


def test_a_systematic_sigma_is_added_in_quadrature() -> None:
    plain = find_peak(Z_UM, gaussian(Z_UM, 0.3))
    biased = find_peak(Z_UM, gaussian(Z_UM, 0.3), PeakSettings(systematic_sigma_um=0.15))
    assert biased.z_um == plain.z_um and biased.flags == plain.flags
    assert biased.sigma_um == pytest.approx(np.hypot(plain.sigma_um, 0.15))
