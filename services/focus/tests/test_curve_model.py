"""The slide's learnt focus curve, and short stacks (3 frames) read with it."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.curve_model import (
    MIN_CURVES,
    CurveModel,
    as_modelled,
    fit_curve,
    fit_short_stack,
    lorentzian,
)
from focustrack_focus.peak import PeakMode, PeakSettings, find_peak, peak_floor_sigma_um
from focustrack_focus.pipeline import FocusSettings, focus_from_curve, pair_result

GAMMA_UM, BACKGROUND, NOISE = 2.5, 0.1, 0.002  # noise as a share of the height


def _curve(z_um: np.ndarray, mu_um: float, rng: np.random.Generator, height: float = 50.0):  # type: ignore[no-untyped-def]
    clean = height * lorentzian(z_um, mu_um, GAMMA_UM, BACKGROUND)
    return clean + NOISE * height * rng.standard_normal(z_um.shape)


def _learnt(rng: np.random.Generator) -> CurveModel:
    model = CurveModel()
    for mu_um in rng.uniform(-1.0, 1.0, MIN_CURVES + 2):
        z = np.arange(-5.0, 5.01, 0.5)
        s = _curve(z, mu_um, rng, height=rng.uniform(20.0, 80.0))
        fit = find_peak(z, s)
        assert model.learn(z, s, fit.z_um, fit.flags)
    return model


def test_a_full_curve_gives_the_shape() -> None:
    rng = np.random.default_rng(0)
    z = np.arange(-5.0, 5.01, 0.5)
    fit = fit_curve(z, _curve(z, 0.3, rng), 0.0)
    assert fit is not None
    assert fit.mu_um == pytest.approx(0.3, abs=0.02)
    assert fit.gamma_um == pytest.approx(GAMMA_UM, rel=0.05)
    assert fit.background == pytest.approx(BACKGROUND, abs=0.03)
    model = _learnt(rng)
    assert model.ready and model.gamma_um == pytest.approx(GAMMA_UM, rel=0.05)
    assert model.noise_share == pytest.approx(NOISE, rel=0.5)
    # short or edge curves teach nothing
    assert not model.learn(z[:5], _curve(z[:5], 0.0, rng), -4.0, frozenset())
    assert not model.learn(z, _curve(z, 0.0, rng), 4.8, frozenset())
    assert not model.learn(z, _curve(z, 0.0, rng), 0.0, frozenset({FocusFlag.MULTI_PEAK}))


def test_short_stacks_locate_the_peak_between_the_outer_frames_with_an_honest_sigma() -> None:
    rng = np.random.default_rng(1)
    model = _learnt(rng)
    z_scores, found = [], 0
    offsets = rng.uniform(-0.45, 0.45, 300)
    for offset in offsets:
        z3 = np.array([-0.5, 0.0, 0.5]) + offset
        s3 = _curve(z3, 0.0, rng)
        fit = fit_short_stack(z3, s3, model, find_peak(z3, s3))
        if fit.z_um is not None and fit.sigma_um is not None:
            found += 1
            z_scores.append(fit.z_um / fit.sigma_um)
        else:  # not located: an edge flag pointing towards the peak, for the retry
            assert fit.flags == {FocusFlag.EDGE_HIGH if offset < 0 else FocusFlag.EDGE_LOW}
    # the model-free reading alone locates only peaks within half a step of the middle
    assert found > 0.8 * len(offsets)
    spread = float(np.std(z_scores))
    assert 0.3 < spread < 1.5
    assert np.mean(np.abs(z_scores) < 3.0) > 0.97


def test_a_peak_beyond_the_stack_stays_an_edge() -> None:
    rng = np.random.default_rng(2)
    model = _learnt(rng)
    z3 = np.array([1.0, 1.5, 2.0])
    s3 = _curve(z3, 0.0, rng)
    fit = fit_short_stack(z3, s3, model, find_peak(z3, s3))
    assert fit.flags == {FocusFlag.EDGE_LOW} and fit.sigma_um is None


def test_the_pipeline_reads_short_stacks_with_a_ready_model_only() -> None:
    rng = np.random.default_rng(3)
    z3 = np.array([-0.1, 0.4, 0.9])  # the peak at 0 is not bracketed by the middle frame
    s3 = _curve(z3, 0.0, rng)
    settings = FocusSettings()
    without = focus_from_curve(z3, s3, settings)
    assert without.flags == {FocusFlag.EDGE_LOW}
    with_model = focus_from_curve(z3, s3, settings, curve=_learnt(rng))
    assert with_model.best_z_um == pytest.approx(0.0, abs=0.15)
    assert with_model.sigma_um is not None and not with_model.flags
    unready = focus_from_curve(z3, s3, settings, curve=CurveModel())
    assert unready.flags == {FocusFlag.EDGE_LOW}


#: An unstained specimen's curve (`_valley`): in focus its contrast floor S0, growing as the
#: square of the defocus (1 per um^2) up to maxima at +-sqrt(2) FADE_UM, fading beyond.
S0, FADE_UM = 0.08, 3.5
VALLEY = FocusSettings(peak=PeakSettings(mode=PeakMode.VALLEY))


def _valley(z_um: np.ndarray, mu_um: float, rng: np.random.Generator) -> np.ndarray:
    u2 = (z_um - mu_um) ** 2
    clean = S0 + u2 * np.exp(-u2 / (2.0 * FADE_UM**2))
    return clean + NOISE * S0 * rng.standard_normal(z_um.shape)


def _valley_model(rng: np.random.Generator) -> CurveModel:
    """The slide's curve learnt from three long valley stacks (16 um, 0.5 um steps)."""
    z = np.arange(-8.0, 8.01, 0.5)
    model = CurveModel()
    for mu_um in rng.uniform(-1.0, 1.0, 3):
        long = focus_from_curve(z, _valley(z, mu_um, rng), VALLEY)
        assert long.best_z_um == pytest.approx(mu_um, abs=0.1) and not long.flags
        assert model.learn(
            *as_modelled(z, long.scores, PeakMode.VALLEY), long.best_z_um, long.flags
        )
    return model


def test_a_valley_is_learnt_and_read_as_its_reciprocal_a_lorentzian() -> None:
    """Near focus s = S0 + (z - mu)^2, whose reciprocal is a Lorentzian of half width
    sqrt(S0): learnt from long stacks (the frames between the two maxima), it reads short
    stacks anywhere between their outer frames, with an honest sigma. Learnt on the raw
    curve, a peak fitted where the curve has its minimum, such stacks came with sigmas of
    11 to 21 um on the simulator's unstained red cells (a scan then took 10 to 20 frames a
    tile)."""
    rng = np.random.default_rng(4)
    model = _valley_model(rng)
    assert model.gamma_um == pytest.approx(np.sqrt(S0), rel=0.25)
    z_scores, found = [], 0
    offsets = rng.uniform(-0.45, 0.45, 300)
    for offset in offsets:
        z3 = np.array([-0.5, 0.0, 0.5]) + offset
        fit = focus_from_curve(z3, _valley(z3, 0.0, rng), VALLEY, curve=model)
        if fit.best_z_um is not None and fit.sigma_um is not None:
            found += 1
            z_scores.append(fit.best_z_um / fit.sigma_um)
            assert fit.sigma_um < 0.25
        else:  # not located: an edge flag pointing towards the valley, for the retry
            assert fit.flags == {FocusFlag.EDGE_HIGH if offset < 0 else FocusFlag.EDGE_LOW}
    assert found > 0.8 * len(offsets)
    assert 0.3 < float(np.std(z_scores)) < 1.5
    assert np.mean(np.abs(z_scores) < 3.0) > 0.97


def test_a_pair_without_the_slides_curve_points_to_its_lower_frame_in_valley_mode() -> None:
    z2, s2 = np.array([0.0, 0.5]), np.array([0.3, 0.1])  # the valley lies above
    assert pair_result(z2, s2, np.inf, VALLEY, 0.0).flags == {FocusFlag.EDGE_HIGH}
    assert pair_result(z2, s2, np.inf, FocusSettings(), 0.0).flags == {FocusFlag.EDGE_LOW}


def test_a_narrow_curves_short_stacks_and_pairs_keep_the_sigma_floor_of_a_long_stack() -> None:
    """A valley's reciprocal is narrow (0.28 um here, 0.13 um on the simulator's red cells):
    read with it, a short stack of clean scores stated 0.00084 um on the simulator, under
    the estimator's nanometre, and the scan ended. Its sigma now carries what `find_peak`
    adds to a long stack's: the sampling floor and the metric's systematic offset."""
    rng = np.random.default_rng(7)
    model = _valley_model(rng)
    settings = FocusSettings(peak=PeakSettings(mode=PeakMode.VALLEY, systematic_sigma_um=0.03))
    floor_um = peak_floor_sigma_um(0.5, settings.peak)
    assert floor_um == pytest.approx(np.hypot(0.02 * 0.5, 0.03))
    sigmas = []
    for offset in rng.uniform(-0.45, 0.45, 100):
        z3 = np.array([-0.5, 0.0, 0.5]) + offset
        stack = focus_from_curve(z3, _valley(z3, 0.0, rng), settings, curve=model)
        pair = pair_result(z3[:2], _valley(z3[:2], 0.0, rng), np.inf, settings, 0.0, curve=model)
        sigmas += [fit.sigma_um for fit in (stack, pair) if fit.sigma_um is not None]
    assert len(sigmas) > 100
    assert min(sigmas) >= floor_um
