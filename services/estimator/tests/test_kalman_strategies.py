"""Kalman strategies driven through the Strategy interface, as the benchmark and service do."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag, Measurement, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.diagnostics import innovation_diagnostics
from focustrack_estimator.filter_params import FilterParams
from focustrack_estimator.kalman_strategies import STRATEGIES, KalmanStrategy
from focustrack_estimator.replay import replay, simulated_measurement


def noisy(truth_um: np.ndarray, sigma_um: float, seed: int) -> np.ndarray:
    return truth_um + np.random.default_rng(seed).normal(0.0, sigma_um, truth_um.shape)


def edge(flag: FocusFlag) -> Measurement:
    return Measurement(z_um=None, flags=frozenset({flag}))


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_every_strategy_completes_a_scan(name: str) -> None:
    truth = generate_surfaces(SurfaceSpec(rows=8, cols=10), 1, seed=0)[0]
    settings = default_settings(ScanGrid(8, 10))
    strategy = registry.create(name, settings)
    result = replay(strategy, truth, noisy(truth, 1.5, seed=0))
    fm = result.focus_map
    for estimate in (fm.prior_um, fm.prior_sigma_um, fm.posterior_um, fm.posterior_sigma_um):
        assert np.all(np.isfinite(estimate))
    assert sum(o.accepted for o in result.outcomes) == 80
    assert not strategy.gave_up.any()
    innovation_um, variance_um2 = strategy.innovations()
    assert innovation_um.shape == variance_um2.shape == (80,)
    assert np.all(fm.posterior_sigma_um <= fm.prior_sigma_um)
    nis = [o.nis for o in result.outcomes if o.accepted]
    np.testing.assert_allclose(nis, innovation_um**2 / variance_um2)
    assert np.max(np.abs(fm.posterior_um - truth)) < 4.0


def test_direction_aware_filter_tracks_a_tilted_plane() -> None:
    rows, cols = np.mgrid[0:12, 0:12]
    truth = 5.0 + 0.4 * cols - 0.3 * rows
    settings = default_settings(ScanGrid(12, 12), noise_sigma_um=0.2)
    result = replay(registry.create("kf-wiener1-dir", settings), truth, noisy(truth, 0.2, seed=1))
    error = np.abs(result.focus_map.posterior_um - truth)
    prior_error = np.abs(result.focus_map.prior_um - truth)[2:]  # once both slopes are seen
    assert error.mean() < 0.1  # below the measurement noise (MAE 0.16 um)
    assert prior_error.mean() < 0.25
    in_focus = np.abs(result.focus_map.z_used_um - truth) <= 0.5
    assert in_focus.mean() > 0.95


def test_zeroth_order_filter_lags_a_slope_the_direction_aware_one_follows() -> None:
    truth = np.tile(0.5 * np.arange(20.0), (6, 1))
    settings = default_settings(ScanGrid(6, 20), noise_sigma_um=0.1)
    measured = noisy(truth, 0.1, seed=2)
    errors = {
        name: np.abs(
            replay(registry.create(name, settings), truth, measured).focus_map.prior_um - truth
        )
        for name in ("kf-wiener0", "kf-wiener1-dir")
    }
    assert errors["kf-wiener1-dir"][2:].mean() < 0.5 * errors["kf-wiener0"][2:].mean()


def first_strategy(**params) -> KalmanStrategy:
    return registry.create("kf-wiener0", default_settings(ScanGrid(2, 3)), params)


def test_edge_flag_retries_the_same_tile_beyond_the_edge_without_predicting() -> None:
    strategy = first_strategy()
    first = strategy.next_acquisition()
    assert (first.row, first.col, first.purpose) == (0, 0, Purpose.SCAN)
    outcome = strategy.record(first, edge(FocusFlag.EDGE_HIGH))
    assert not outcome.accepted
    retry = strategy.next_acquisition()
    assert (retry.row, retry.col, retry.purpose) == (0, 0, Purpose.RETRY)
    assert retry.z.low_um < first.z.high_um < retry.z.high_um  # continues past the edge
    assert retry.predicted_um == first.predicted_um  # no second predict
    assert retry.predicted_sigma_um == first.predicted_sigma_um
    strategy.record(retry, Measurement(z_um=retry.z.high_um - 1.0))
    gain = 10.0**2 / (10.0**2 + 1.5**2)  # start sigma 10 um, measurement noise 1.5 um
    assert strategy.map.posterior_um[0, 0] == pytest.approx(gain * (retry.z.high_um - 1.0))
    following = strategy.next_acquisition()
    assert (following.row, following.col, following.purpose) == (0, 1, Purpose.SCAN)


FLAT = Measurement(z_um=None, flags=frozenset({FocusFlag.FLAT}))


def test_flat_curve_retries_a_wide_stack_in_place_once() -> None:
    strategy = first_strategy()
    strategy.record(strategy.next_acquisition(), Measurement(z_um=0.0))
    narrow = strategy.next_acquisition()
    assert narrow.z.n_frames < strategy.settings.policy.max_frames
    strategy.record(narrow, FLAT)
    wide = strategy.next_acquisition()
    assert (wide.row, wide.col, wide.purpose) == (narrow.row, narrow.col, Purpose.RETRY)
    assert wide.z.center_um == pytest.approx(narrow.z.center_um)
    assert wide.z.n_frames == strategy.settings.policy.max_frames
    outcome = strategy.record(wide, FLAT)  # flat in the widest stack too: give the tile up
    assert outcome.posterior_um == outcome.prior_um
    assert strategy.gave_up[narrow.row, narrow.col]
    assert strategy.next_acquisition().purpose is Purpose.SCAN


def test_an_empty_field_is_given_up_without_a_retry() -> None:
    strategy = first_strategy()
    first = strategy.next_acquisition()
    empty = Measurement(z_um=None, flags=frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))
    outcome = strategy.record(first, empty)
    assert not outcome.accepted and outcome.posterior_um == outcome.prior_um
    following = strategy.next_acquisition()
    assert (following.row, following.col, following.purpose) == (0, 1, Purpose.SCAN)


def test_peak_between_two_stacks_is_looked_for_in_the_gap() -> None:
    strategy = first_strategy()
    first = strategy.next_acquisition()
    strategy.record(first, edge(FocusFlag.EDGE_HIGH))
    above = strategy.next_acquisition()
    strategy.record(above, edge(FocusFlag.EDGE_LOW))  # the peak is between the two stacks
    gap = strategy.next_acquisition()
    assert gap.z.low_um <= first.z.high_um and gap.z.high_um >= above.z.low_um
    assert gap.z.n_frames < strategy.settings.policy.max_frames


def test_a_tile_is_given_up_after_max_retries_and_imaged_at_its_prediction() -> None:
    strategy = first_strategy(max_retries=2)
    first = strategy.next_acquisition()
    flags = [FocusFlag.EDGE_HIGH, FocusFlag.EDGE_HIGH, FocusFlag.FLAT]
    for flag in flags:
        acquisition = strategy.next_acquisition()
        assert (acquisition.row, acquisition.col) == (0, 0)
        outcome = strategy.record(acquisition, edge(flag))
    assert strategy.gave_up[0, 0] and not outcome.accepted
    assert outcome.posterior_um == first.predicted_um
    assert strategy.map.z_used_um[0, 0] == pytest.approx(first.predicted_um)
    assert (strategy.next_acquisition().row, strategy.next_acquisition().col) == (0, 1)
    assert strategy.innovations()[0].size == 0


def test_a_scan_always_ends_even_without_any_peak() -> None:
    strategy = first_strategy(max_retries=1)
    n_acquisitions = 0
    while (acquisition := strategy.next_acquisition()) is not None:
        strategy.record(acquisition, edge(FocusFlag.EDGE_LOW))
        n_acquisitions += 1
    assert n_acquisitions == 2 * 6 and strategy.gave_up.all()


def run_log(name: str, truth: np.ndarray, measured: np.ndarray) -> list:
    """A scan's (acquisition, measurement) log, with some flat curves among the stacks."""
    strategy = registry.create(name, default_settings(ScanGrid(*truth.shape)))
    log = []
    while (acquisition := strategy.next_acquisition()) is not None:
        if acquisition.index % 17 == 5:
            measurement = Measurement(z_um=None, flags=frozenset({FocusFlag.FLAT}))
        else:
            measurement = simulated_measurement(
                acquisition, measured[acquisition.row, acquisition.col]
            )
        strategy.record(acquisition, measurement)
        log.append((acquisition, measurement))
    return log


@pytest.mark.parametrize("name", ["kf-wiener2", "kf-wiener1-dir"])
def test_replaying_the_measurement_log_rebuilds_the_same_state(name: str) -> None:
    truth = generate_surfaces(SurfaceSpec(rows=6, cols=7), 1, seed=4)[0]
    log = run_log(name, truth, noisy(truth, 1.5, seed=4))
    original = registry.create(name, default_settings(ScanGrid(6, 7)))
    rebuilt = registry.create(name, default_settings(ScanGrid(6, 7)))
    half = len(log) // 2
    for acquisition, measurement in log:
        original.record(acquisition, measurement)
    for acquisition, measurement in log[:half]:
        rebuilt.record(acquisition, measurement)
    assert rebuilt.next_acquisition() == log[half][0]  # the service's next answer after restart
    for acquisition, measurement in log[half:]:
        rebuilt.record(acquisition, measurement)
    for field in ("prior_um", "prior_sigma_um", "posterior_um", "posterior_sigma_um", "z_used_um"):
        np.testing.assert_array_equal(getattr(rebuilt.map, field), getattr(original.map, field))
    np.testing.assert_array_equal(rebuilt.innovations(), original.innovations())
    assert rebuilt.next_acquisition() is None


def test_per_measurement_sigma_is_used_as_r() -> None:
    confident, default = first_strategy(), first_strategy()
    for strategy in (confident, default):
        strategy.record(strategy.next_acquisition(), Measurement(z_um=1.0))
    sharp = Measurement(z_um=3.0, sigma_um=0.1)
    outcome = confident.record(confident.next_acquisition(), sharp)
    plain = default.record(default.next_acquisition(), Measurement(z_um=3.0))
    assert outcome.posterior_sigma_um < 0.1 < plain.posterior_sigma_um
    assert abs(outcome.posterior_um - 3.0) < 0.01 < abs(plain.posterior_um - 3.0)
    variance_um2 = confident.innovations()[1][-1]
    assert variance_um2 == pytest.approx(outcome.prior_sigma_um**2 + 0.1**2)


def test_height_noise_helps_on_an_isolated_jump() -> None:
    columns = np.arange(60.0)
    truth = (0.05 * columns + np.where(columns >= 30, 3.0, 0.0))[None, :]  # a fold at column 30
    measured = noisy(truth, 0.3, seed=3)
    settings = default_settings(ScanGrid(1, 60), noise_sigma_um=0.3)

    def error_after_jump(q_height_um2: float) -> float:
        strategy = registry.create(
            "kf-wiener1", settings, {"q": 1e-4, "q_height_um2": q_height_um2}
        )
        prior = replay(strategy, truth, measured).focus_map.prior_um
        return float(np.abs(prior - truth)[0, 31:].mean())

    assert error_after_jump(0.3) < 0.8 * error_after_jump(0.0)


def test_innovations_are_white_only_when_the_model_fits() -> None:
    # A 0th-order surface: a random walk of variance q per tile along the serpentine path.
    grid = ScanGrid(20, 20)
    rng = np.random.default_rng(5)
    walk = np.cumsum(rng.normal(0.0, np.sqrt(0.2), grid.n_tiles))
    truth = np.empty(grid.shape)
    for tile, height in zip(grid.serpentine, walk, strict=True):
        truth[tile.row, tile.col] = height
    measured = noisy(truth, 1.5, seed=6)

    def diagnose(q: float):
        strategy = registry.create("kf-wiener0", default_settings(grid), {"q": q})
        replay(strategy, truth, measured)
        return innovation_diagnostics(*strategy.innovations())

    matched = diagnose(0.2)
    assert matched.white and matched.consistent and matched.zero_mean
    too_stiff = diagnose(1e-4)
    assert not too_stiff.white and not too_stiff.consistent


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_each_strategy_takes_the_loops_options_as_parameters(name: str) -> None:
    assert issubclass(STRATEGIES[name].params, FilterParams)
    strategy = registry.create(name, default_settings(ScanGrid(2, 2)), {"gate_patience": 4})
    assert isinstance(strategy, KalmanStrategy) and strategy.name == name
    assert strategy.options.gate_patience == 4  # read by the loop, from construction on
    # To a user, the options are parameters like the others.
    assert {"max_retries", "sqrt", "gate_nis", "gate_patience", "adapt_r"} <= set(
        registry.parameters(name)
    )


def test_bad_parameters_are_clear_errors() -> None:
    settings = default_settings(ScanGrid(2, 2))
    with pytest.raises(ValueError, match="max_retries"):
        registry.create("kf-wiener0", settings, {"max_retries": -1})
    with pytest.raises(ValueError, match="beta"):
        registry.create("kf-gm1", settings, {"beta_per_tile": 2.0})
    with pytest.raises(ValueError, match="q"):
        registry.create("kf-wiener1", settings, {"q": -1.0})


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_square_root_form_agrees_with_the_covariance_form(name: str) -> None:
    truth = generate_surfaces(SurfaceSpec(rows=8, cols=9), 1, seed=7)[0]
    measured = noisy(truth, 1.5, seed=7)
    settings = default_settings(ScanGrid(8, 9))
    plain = replay(registry.create(name, settings), truth, measured).focus_map
    root = replay(registry.create(name, settings, {"sqrt": True}), truth, measured).focus_map
    for layer in (
        "prior_um",
        "prior_sigma_um",
        "posterior_um",
        "posterior_sigma_um",
        "smoothed_um",
    ):
        np.testing.assert_allclose(getattr(root, layer), getattr(plain, layer), atol=1e-7)
    np.testing.assert_allclose(root.z_used_um, plain.z_used_um, atol=1e-7)


def test_partitioned_update_runs_in_the_square_root_form_too() -> None:
    truth = generate_surfaces(SurfaceSpec(rows=6, cols=6), 1, seed=8)[0]
    measured = noisy(truth, 1.5, seed=8)
    settings = default_settings(ScanGrid(6, 6))
    maps = [
        replay(
            registry.create("kf-wiener1-dir", settings, {"partitioned": True, "sqrt": sqrt}),
            truth,
            measured,
        )
        for sqrt in (False, True)
    ]
    np.testing.assert_allclose(maps[1].focus_map.posterior_um, maps[0].focus_map.posterior_um)
