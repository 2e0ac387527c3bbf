"""The slide's scale on the focus service's sigma (`sigma_scale`): a metric that states a
sigma three times too small is caught in the first rows of a simulated scan; an honest
one keeps a scale of exactly 1."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from focustrack_core.domain import Measurement, Outcome
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import family_spec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.diagnose import diagnose
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.sigma_scale import MAX_SCALE, SigmaScale
from focustrack_estimator.strategy import Strategy

ROWS, COLS = 12, 20
TRUE_SIGMA_UM = 0.3


def scan(stated_sigma_um: float, seed: int) -> tuple[Strategy, list[float]]:
    """A simulated scan (kf-2d, a filter consistent on these surfaces) whose focus service
    errs with TRUE_SIGMA_UM but states `stated_sigma_um`: the strategy at its end, and the
    slide's sigma scale after each acquisition."""
    truth = generate_surfaces(family_spec("standard", ROWS, COLS), 1, seed=seed)[0]
    measured = truth + np.random.default_rng(seed).normal(0.0, TRUE_SIGMA_UM, truth.shape)
    strategy = registry.create("kf-2d", default_settings(ScanGrid(ROWS, COLS)), {})
    scales = []
    while (acquisition := strategy.next_acquisition()) is not None:
        result = simulated_measurement(acquisition, measured[acquisition.row, acquisition.col])
        if result.is_observation:
            result = dataclasses.replace(result, sigma_um=stated_sigma_um)
        strategy.record(acquisition, result)
        scales.append(strategy.sigma_scale.scale)
    return strategy, scales


@pytest.mark.parametrize("seed", [1, 2])
def test_a_three_times_overconfident_metric_is_caught_in_the_first_rows(seed: int) -> None:
    strategy, scales = scan(TRUE_SIGMA_UM / 3.0, seed)
    first_rows = scales[: 3 * COLS]  # about the first three rows' acquisitions
    assert first_rows[-1] >= 2.2, first_rows
    assert 2.4 <= scales[-1] <= 3.6
    assert diagnose([], strategy).sigma_scale == scales[-1]  # reported in the diagnostics


@pytest.mark.parametrize("seed", [1, 2])
def test_an_honest_metric_keeps_its_sigma(seed: int) -> None:
    assert set(scan(TRUE_SIGMA_UM, seed)[1]) == {1.0}


def outcome(innovation_um: float, nis: float) -> Outcome:
    return Outcome(0, 0, True, innovation_um=innovation_um, nis=nis)


def test_the_scale_waits_for_evidence_and_stays_bounded() -> None:
    scale = SigmaScale()
    stated = Measurement(0.0, 0.1)
    scale.learn(stated, outcome(0.5, 25.0))  # one 5-sigma miss: not yet evidence
    assert scale.scale == 1.0 and scale.scaled(stated) is stated
    for _ in range(40):  # every innovation 100 sigmas: each capped, the scale bounded
        scale.learn(stated, outcome(10.0, 1e4))
    assert 4.5 < scale.scale <= MAX_SCALE
    assert scale.scaled(stated).sigma_um == pytest.approx(0.1 * scale.scale)
    assert scale.scaled(Measurement(None)) == Measurement(None)  # nothing to scale
