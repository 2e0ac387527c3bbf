"""Thermal drift: settling plus a random walk, the same for a seed whatever is asked."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.drift import ThermalDrift


def test_settling_alone_is_an_exponential_approach() -> None:
    drift = ThermalDrift(settle_um=2.0, settle_tau_s=200.0)
    assert drift.at(0.0) == 0.0
    assert drift.at(200.0) == pytest.approx(2.0 * (1 - np.exp(-1)))
    assert drift.at(1e6) == pytest.approx(2.0)


def test_the_walk_is_the_same_for_a_seed_in_any_order_and_differs_between_seeds() -> None:
    times = np.array([7000.5, 3.25, 3599.9, 3600.0, 12.0])
    forward = ThermalDrift(walk_um_per_sqrt_min=0.3, seed=1).array(times)
    backward = ThermalDrift(walk_um_per_sqrt_min=0.3, seed=1)
    one_by_one = [backward.at(t) for t in times[::-1]][::-1]
    np.testing.assert_allclose(forward, one_by_one)
    assert not np.allclose(forward, ThermalDrift(walk_um_per_sqrt_min=0.3, seed=2).array(times))


def test_the_walk_spreads_as_stated() -> None:
    # 0.3 um per sqrt(minute): after 9 minutes a std of 0.9 um over many seeds
    ends = [ThermalDrift(walk_um_per_sqrt_min=0.3, seed=s).at(540.0) for s in range(400)]
    assert np.std(ends) == pytest.approx(0.9, rel=0.15)
    assert abs(np.mean(ends)) < 0.15


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="settle_tau_s"):
        ThermalDrift(settle_tau_s=0.0)
    with pytest.raises(ValueError, match="walk_um_per_sqrt_min"):
        ThermalDrift(walk_um_per_sqrt_min=-1.0)
