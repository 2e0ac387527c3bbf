"""The model bank (`kf-mmae`): members blended by likelihood, with a weight floor."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import SlideSettings
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
from focustrack_estimator.bank import ModelBank
from focustrack_estimator.filter_params import FilterParams
from focustrack_estimator.kalman_strategies import KalmanStrategy, PathFilter
from focustrack_estimator.models import WienerModel
from focustrack_estimator.replay import replay, score


def random_walk_surface(grid: ScanGrid, q: float, seed: int) -> np.ndarray:
    """A 0th-order surface: a random walk of variance q per tile along the serpentine path."""
    walk = np.cumsum(np.random.default_rng(seed).normal(0.0, np.sqrt(q), grid.n_tiles))
    truth = np.empty(grid.shape)
    for tile, height in zip(grid.serpentine, walk, strict=True):
        truth[tile.row, tile.col] = height
    return truth


def bank_strategy(settings: SlideSettings, qs: list[float], floor: float) -> KalmanStrategy:
    members = [PathFilter(WienerModel(0, q), settings, sqrt=False) for q in qs]
    bank = ModelBank(members, weight_floor=floor, nis_clip=4.0)
    return KalmanStrategy(settings, bank, name="bank", options=FilterParams())


def test_the_weights_find_the_process_noise_of_the_surface() -> None:
    grid = ScanGrid(20, 20)
    truth = random_walk_surface(grid, q=1.0, seed=1)
    measured = truth + np.random.default_rng(2).normal(0.0, 0.5, truth.shape)
    settings = default_settings(grid, noise_sigma_um=0.5)
    strategy = bank_strategy(settings, [0.01, 1.0, 100.0], floor=1e-3)
    replay(strategy, truth, measured)
    weights = strategy.estimator.weights
    assert np.argmax(weights) == 1 and weights[1] > 0.9
    assert weights.min() >= 1e-3 * 0.99 and weights.sum() == pytest.approx(1.0)


def test_a_bank_of_one_is_that_filter() -> None:
    truth = generate_surfaces(family_spec("standard", 8, 8), 1, seed=3)[0]
    measured = add_measurement_noise(truth[None], 1.5, seed=3)[0]
    settings = default_settings(ScanGrid(8, 8))
    single = replay(registry.create("kf-wiener0", settings), truth, measured).focus_map
    bank = replay(bank_strategy(settings, [0.14], floor=0.0), truth, measured).focus_map
    for layer in ("prior_um", "posterior_um", "posterior_sigma_um", "smoothed_um"):
        np.testing.assert_allclose(getattr(bank, layer), getattr(single, layer), atol=1e-12)


@pytest.mark.parametrize("family", ["standard", "steps", "tilted", "outliers"])
def test_the_bank_is_as_good_as_the_best_single_model_on_every_family(family: str) -> None:
    # Training seeds, not the reported ones; small maps to stay fast.
    truths = generate_surfaces(family_spec(family, 14, 14), 6, seed=5)
    measured = add_measurement_noise(truths, 1.5, seed=5)
    if family in OUTLIERS:
        measured = add_outliers(measured, OUTLIERS[family], seed=5)
    settings = default_settings(ScanGrid(14, 14))

    def prior_mae(name: str) -> float:
        runs = [
            replay(registry.create(name, settings), t, m)
            for t, m in zip(truths, measured, strict=True)
        ]
        return score(runs, settings.dof_um).prior_mae_um

    best_single = min(prior_mae("kf-wiener0"), prior_mae("kf-wiener1-dir"))
    assert prior_mae("kf-mmae") <= 1.02 * best_single


def test_bad_bank_parameters_are_clear_errors() -> None:
    settings = default_settings(ScanGrid(3, 3))
    for bad in ({"weight_floor": 0.5}, {"q_spread": 0.5}, {"nis_clip": 0.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            registry.create("kf-mmae", settings, bad)
    members = [PathFilter(WienerModel(0, 0.1), settings, sqrt=False)] * 2
    with pytest.raises(ValueError, match="weight_floor"):  # 1/2 for two members
        ModelBank(members, weight_floor=0.5, nis_clip=1.0)
    with pytest.raises(ValueError, match="at least one member"):
        ModelBank([], weight_floor=0.0, nis_clip=1.0)
