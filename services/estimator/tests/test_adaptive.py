"""Noise that adapts: the NIS gate (outliers vs real steps) and the online default R."""

from __future__ import annotations

import pytest

from focustrack_core.domain import Measurement
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import (
    OUTLIERS,
    add_measurement_noise,
    add_outliers,
    family_spec,
    generate_surfaces,
)
from focustrack_estimator import registry
from focustrack_estimator.diagnostics import nis_gate
from focustrack_estimator.replay import replay, score


def scan_row(name: str, heights_um: list[float], **params):
    """Feed one row of measured heights to a strategy; returns it and its outcomes."""
    strategy = registry.create(name, default_settings(ScanGrid(1, len(heights_um))), params)
    outcomes = [
        strategy.record(strategy.next_acquisition(), Measurement(z_um=z_um)) for z_um in heights_um
    ]
    return strategy, outcomes


def test_an_outlier_is_rejected_counted_and_reported_with_its_nis() -> None:
    heights = [0.1, -0.2, 0.0, 0.2, -0.1, 9.0, 0.1, -0.1]
    strategy, outcomes = scan_row("kf-wiener0", heights, gate_nis=nis_gate(0.999))
    outlier = outcomes[5]
    assert not outlier.accepted and outlier.nis > nis_gate(0.999)
    assert outlier.innovation_um == pytest.approx(9.0 - outlier.prior_um)
    assert outlier.posterior_um == outlier.prior_um  # the tile keeps its prediction
    assert strategy.gated.sum() == 1 and strategy.gated[0, 5]
    assert all(o.accepted for i, o in enumerate(outcomes) if i != 5)
    assert strategy.innovations()[0].size == len(heights) - 1
    assert abs(outcomes[6].prior_um) < 0.5  # the track was not pulled towards 9 um


def test_consecutive_outliers_are_a_real_step_and_the_filter_follows_it() -> None:
    heights = [0.0, 0.1, -0.1, 0.0, 6.0, 6.1, 5.9, 6.0, 6.0]  # a step after 4 tiles
    strategy, outcomes = scan_row("kf-wiener0", heights, gate_nis=10.0, gate_patience=1)
    assert not outcomes[4].accepted and outcomes[5].accepted  # one rejection, then the step
    assert outcomes[5].posterior_um > 4.5  # the inflated P lets the step in at once
    assert abs(outcomes[-1].posterior_um - 6.0) < 0.5
    assert strategy.gated.sum() == 1


def test_gating_helps_on_the_outliers_family() -> None:
    truths = generate_surfaces(family_spec("outliers", 20, 20), 8, seed=7)
    measured = add_outliers(add_measurement_noise(truths, 1.5, 7), OUTLIERS["outliers"], 7)
    settings = default_settings(ScanGrid(20, 20))

    def prior_mae(**params) -> float:
        runs = [
            replay(registry.create("kf-wiener1-dir", settings, params), t, m)
            for t, m in zip(truths, measured, strict=True)
        ]
        return score(runs, settings.dof_um).prior_mae_um

    assert prior_mae(gate_nis=16.0) < 0.98 * prior_mae()


def test_the_default_r_is_estimated_from_the_innovations() -> None:
    # The slide's focus measurements are far better than the configured 1.5 um.
    truths = generate_surfaces(family_spec("standard", 20, 20), 2, seed=9)
    measured = add_measurement_noise(truths, 0.3, seed=9)
    settings = default_settings(ScanGrid(20, 20), noise_sigma_um=1.5)
    maes = {}
    for adapt_r in (False, True):
        runs = []
        for truth, measured_um in zip(truths, measured, strict=True):
            strategy = registry.create("kf-wiener1-dir", settings, {"adapt_r": adapt_r})
            runs.append(replay(strategy, truth, measured_um))
            if adapt_r:
                # From 2.25 um^2 towards 0.09 um^2; the model's own error is counted in too.
                assert 0.3**2 < strategy.default_r_um2 < 0.25 * 1.5**2
        maes[adapt_r] = score(runs, settings.dof_um).post_mae_um
    assert maes[True] < 0.8 * maes[False]


def test_a_measurements_own_sigma_is_not_used_to_estimate_the_default_r() -> None:
    heights = [3.0, -3.0] * 10
    strategy, _ = scan_row("kf-wiener0", heights, adapt_r=True)
    assert strategy.default_r_um2 > 1.5**2  # large innovations: R grows
    sharp = registry.create("kf-wiener0", default_settings(ScanGrid(1, 20)), {"adapt_r": True})
    for z_um in heights:
        sharp.record(sharp.next_acquisition(), Measurement(z_um=z_um, sigma_um=0.2))
    assert sharp.default_r_um2 == pytest.approx(1.5**2)


def test_gating_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="gate_nis"):
        registry.create("kf-wiener0", default_settings(ScanGrid(2, 2)), {"gate_nis": -1.0})
    assert nis_gate(0.99) == pytest.approx(6.635, abs=1e-3)
    with pytest.raises(ValueError, match="probability"):
        nis_gate(1.0)
