"""The simulator's thermal drift: warm-up settling and a random walk per seed, on the stage."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.drift import ThermalDrift
from focustrack_instrument_sim.simulated import microscope_from_options, thermal_drift
from focustrack_instrument_sim.simulator_options import SimulatorOptions


def _options(**changes: object) -> SimulatorOptions:
    return SimulatorOptions.model_validate(
        {"rows": 2, "cols": 3, "height": 64, "width": 64, "seed": 5, **changes}
    )


def test_no_settling_and_no_walk_is_no_thermal_drift() -> None:
    assert thermal_drift(_options()) is None
    assert thermal_drift(_options(drift_um_per_s=0.01)) is None


def test_the_focus_drifts_by_the_seeds_settling_and_walk_plus_the_linear_rate() -> None:
    options = _options(
        drift_settle_um=2.0, drift_settle_tau_s=5.0, drift_walk_um_per_sqrt_min=0.3,
        drift_um_per_s=0.001,
    )  # fmt: skip
    scope = microscope_from_options(options)
    for col in (1, 2, 0):
        scope.acquire("slide-0", 0, col, 0.0, 0.5, 9)
    clock_s = scope.stage.clock_s
    expected = ThermalDrift(2.0, 5.0, 0.3, seed=5).at(clock_s) + 0.001 * clock_s
    truth_um, drift_um = scope.truth_um("slide-0")
    assert drift_um == pytest.approx(expected)
    assert drift_um > 0.1  # settling of 2 um with tau 5 s, over the stacks' half second
    np.testing.assert_allclose(truth_um - scope.slides["slide-0"].focus_um, drift_um)
    # frames are rendered at the drift of their own exposure
    times_s = np.array([0.1, 0.2])
    np.testing.assert_allclose(
        scope.stage.drift_um(times_s),
        ThermalDrift(2.0, 5.0, 0.3, seed=5).array(times_s) + 0.001 * times_s,
    )
