"""The slide's learnt focus curve, and short stacks (3 frames) read with it."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.curve_model import (
    MIN_CURVES,
    CurveModel,
    fit_curve,
    fit_short_stack,
    lorentzian,
)
from focustrack_focus.peak import find_peak
from focustrack_focus.pipeline import FocusSettings, focus_from_curve

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
