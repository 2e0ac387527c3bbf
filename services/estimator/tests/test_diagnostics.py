"""Innovation diagnostics: white sequences pass, correlated, biased or mis-scaled ones fail."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_estimator.diagnostics import autocorrelation, innovation_diagnostics

N = 800


def varying_variances(rng: np.random.Generator) -> np.ndarray:
    """Predicted variances that change along the scan, as a filter's do (um^2)."""
    return rng.uniform(0.5, 4.0, N)


def test_white_sequence_passes() -> None:
    rng = np.random.default_rng(1)
    variance = varying_variances(rng)
    innovation = rng.standard_normal(N) * np.sqrt(variance)
    result = innovation_diagnostics(innovation, variance)
    assert result.white and result.zero_mean and result.consistent
    assert result.autocorrelation[0] == pytest.approx(1.0)
    within = np.abs(result.autocorrelation[1:]) <= result.autocorrelation_bound
    assert within.mean() >= 0.85  # about 95% expected
    assert result.mean_nis == pytest.approx(1.0, abs=0.15)


def test_correlated_sequence_fails() -> None:
    rng = np.random.default_rng(2)
    ar = np.zeros(N)
    for k in range(1, N):  # AR(1): what a filter with too little process noise leaves behind
        ar[k] = 0.6 * ar[k - 1] + rng.standard_normal()
    result = innovation_diagnostics(ar, np.full(N, ar.var()))
    assert not result.white
    assert result.ljung_box_p < 1e-6
    assert result.autocorrelation[1] == pytest.approx(0.6, abs=0.08)
    assert result.autocorrelation[1] > result.autocorrelation_bound


def test_biased_or_overconfident_sequences_fail() -> None:
    rng = np.random.default_rng(3)
    white = rng.standard_normal(N)
    assert not innovation_diagnostics(white + 0.3, np.ones(N)).zero_mean
    overconfident = innovation_diagnostics(2.0 * white, np.ones(N))
    assert not overconfident.consistent
    assert overconfident.mean_nis == pytest.approx(4.0, rel=0.15)


def test_autocorrelation_of_an_alternating_sequence() -> None:
    rho = autocorrelation(np.array([1.0, -1.0] * 50), 2)
    np.testing.assert_allclose(rho, [1.0, -0.99, 0.98])


@pytest.mark.parametrize(
    ("innovation", "variance", "message"),
    [
        (np.zeros(30), np.ones(29), "one length"),
        (np.zeros(10), np.ones(10), "more than"),
        (np.ones(30), -np.ones(30), "positive"),
        (np.full(30, np.nan), np.ones(30), "finite"),
    ],
)
def test_bad_input_is_a_clear_error(
    innovation: np.ndarray, variance: np.ndarray, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        innovation_diagnostics(innovation, variance)
