"""2-D strategies: complete scans, the row above is used, the reduced update and pruning."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag, FocusMap, Measurement, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.nshp import nshp_weights
from focustrack_estimator.replay import replay
from focustrack_estimator.spatial import RowBankFilter

#: The 2-D strategies this file checks (kf-2d-lean is kf-2d with the lean rule: test_lean.py).
STRATEGIES = ("kf-2d", "nshp-wiener0", "nshp-wiener1")

NOISE_UM = 1.5


def _maps(rows: int, cols: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    truth_um = generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed)[0]
    noise_um = np.random.default_rng([seed, 7]).normal(0.0, NOISE_UM, truth_um.shape)
    return truth_um, truth_um + noise_um


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_scan_completes_and_is_deterministic(name: str) -> None:
    truth_um, measured_um = _maps(6, 5, seed=11)
    settings = default_settings(ScanGrid(6, 5))
    first = replay(registry.create(name, settings), truth_um, measured_um)
    second = replay(registry.create(name, settings), truth_um, measured_um)
    fm = first.focus_map
    for array in (fm.prior_um, fm.prior_sigma_um, fm.posterior_um, fm.z_used_um):
        assert np.all(np.isfinite(array))
    assert sum(o.accepted for o in first.outcomes) == 30  # every tile measured once
    assert np.mean(np.abs(fm.posterior_um - truth_um)) < NOISE_UM  # it filters the noise
    for a, b in zip(
        (fm.prior_um, fm.posterior_um, fm.z_used_um),
        (second.focus_map.prior_um, second.focus_map.posterior_um, second.focus_map.z_used_um),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", sorted(STRATEGIES))
def test_edge_peak_is_reacquired_beyond_the_edge(name: str) -> None:
    truth_um, _ = _maps(4, 4, seed=5)
    measured_um = truth_um.copy()
    measured_um[1, 2] += 8.0  # above a stack centred on the prediction
    result = replay(registry.create(name, default_settings(ScanGrid(4, 4))), truth_um, measured_um)
    on_tile = [o for o in result.outcomes if (o.row, o.col) == (1, 2)]
    assert len(on_tile) > 1 and not on_tile[0].accepted and on_tile[-1].accepted
    assert on_tile[-1].innovation_um is not None and on_tile[-1].innovation_um > 5.0


def test_measurement_sigma_is_used_as_r() -> None:
    """A measurement with a large sigma moves the estimate less than one with a small sigma."""
    settings = default_settings(ScanGrid(3, 3), start_sigma_um=5.0)
    posteriors = []
    for sigma_um in (0.1, 10.0):
        strategy = registry.create("kf-2d", settings)
        acquisition = strategy.next_acquisition()
        assert acquisition is not None and acquisition.purpose is Purpose.SCAN
        outcome = strategy.record(acquisition, Measurement(z_um=2.0, sigma_um=sigma_um))
        posteriors.append(outcome.posterior_um)
    assert posteriors[0] == pytest.approx(2.0, abs=0.05)
    assert abs(posteriors[1]) < 1.0


def test_peakless_stacks_are_retried_then_the_prior_stands() -> None:
    strategy = registry.create("nshp-wiener0", default_settings(ScanGrid(2, 2)), {"max_retries": 2})
    edge = Measurement(None, flags=frozenset({FocusFlag.EDGE_HIGH}))
    outcomes = []
    for _ in range(3):
        acquisition = strategy.next_acquisition()
        assert acquisition is not None and (acquisition.row, acquisition.col) == (0, 0)
        outcomes.append(strategy.record(acquisition, edge))
    assert [o.accepted for o in outcomes] == [False, False, False]
    assert outcomes[-1].posterior_um == outcomes[-1].prior_um
    following = strategy.next_acquisition()
    assert following is not None and (following.row, following.col) == (0, 1)


def _random_walk_prior_mae(truth_um: np.ndarray, measured_um: np.ndarray, q_um2: float) -> float:
    """Prior MAE of a scalar random-walk Kalman filter along the serpentine (the 1-D baseline)."""
    grid = ScanGrid(*truth_um.shape)
    mean_um, var_um2, errors = 0.0, 100.0, []
    for tile in grid.serpentine:
        errors.append(abs(mean_um - truth_um[tile.row, tile.col]))
        gain = var_um2 / (var_um2 + NOISE_UM**2)
        mean_um += gain * (measured_um[tile.row, tile.col] - mean_um)
        var_um2 = (1.0 - gain) * var_um2 + q_um2
    return float(np.mean(errors))


def test_kf_2d_uses_the_row_above() -> None:
    """On a slide tilted along y only, the rows above tell the height of the next row.

    A 1-D random walk along the path must re-learn each row's height from the
    row's own noisy measurements; kf-2d carries the previous row (and the
    y-slope learnt from the rows) across. The baseline gets its best q in hindsight.
    """
    rows, cols = 12, 12
    row_height_um = 1.5 * np.arange(rows)
    truth_um = np.repeat(row_height_um[:, None], cols, axis=1)
    kf_2d_mae, baseline_mae = [], []
    for seed in range(3):
        noise_um = np.random.default_rng(seed).normal(0.0, NOISE_UM, truth_um.shape)
        measured_um = truth_um + noise_um
        settings = default_settings(ScanGrid(rows, cols), noise_sigma_um=NOISE_UM)
        result = replay(registry.create("kf-2d", settings), truth_um, measured_um)
        kf_2d_mae.append(np.mean(np.abs(result.focus_map.prior_um - truth_um)))
        baseline_mae.append(
            min(
                _random_walk_prior_mae(truth_um, measured_um, q) for q in (0.03, 0.1, 0.3, 1.0, 3.0)
            )
        )
    assert np.mean(kf_2d_mae) < 0.8 * np.mean(baseline_mae)


def test_nshp_weights_reproduce_constants_and_planes() -> None:
    offsets = np.array([(0, -1), (-1, -1), (-1, 0), (-1, 1)], dtype=float)
    plane = 2.0 + 0.3 * offsets[:, 0] - 0.7 * offsets[:, 1]  # height at (0, 0) is 2.0
    for order in (0, 1):
        w = nshp_weights(offsets, order)
        assert w.sum() == pytest.approx(1.0)
        assert w @ np.full(4, 5.0) == pytest.approx(5.0)
    assert nshp_weights(offsets, 1) @ plane == pytest.approx(2.0)
    in_row = np.array([(0, -1), (0, -2)], dtype=float)  # no y-spread: the x-line only
    assert nshp_weights(in_row, 1) @ np.array([1.0, 0.0]) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="order"):
        nshp_weights(offsets, 2)


def _kf_2d_scan(
    rows: int, cols: int, seed: int, **params: float
) -> tuple[RowBankFilter, FocusMap, np.ndarray]:
    truth_um, measured_um = _maps(rows, cols, seed)
    strategy = registry.create("kf-2d", default_settings(ScanGrid(rows, cols)), params)
    assert isinstance(strategy, RowBankFilter)
    return strategy, replay(strategy, truth_um, measured_um).focus_map, truth_um


def _mae(estimate_um: np.ndarray, truth_um: np.ndarray) -> float:
    return float(np.mean(np.abs(estimate_um - truth_um)))


def test_reduced_update_stays_close_to_the_full_filter_with_a_consistent_covariance() -> None:
    """A window of 8 columns on a 30-column slide: far columns are not corrected by a
    measurement; the covariance stays that of the reduced estimator (symmetric, PSD)."""
    rows, cols = 6, 30
    reduced, reduced_map, truth_um = _kf_2d_scan(rows, cols, 2, window_cols=8)
    _, full_map, _ = _kf_2d_scan(rows, cols, 2, window_cols=cols)
    assert not np.array_equal(reduced_map.prior_um, full_map.prior_um)  # not the full filter
    assert _mae(reduced_map.prior_um, truth_um) < 1.1 * _mae(full_map.prior_um, truth_um)
    P = reduced.P
    np.testing.assert_allclose(P, P.transpose(0, 2, 1), rtol=1e-12, atol=1e-14)
    assert np.linalg.eigvalsh(P).min() > -1e-9


def test_pruning_drops_members_without_changing_the_estimates_much() -> None:
    pruned, pruned_map, truth_um = _kf_2d_scan(12, 12, 4, prune_log_weight=5.0)
    kept, kept_map, _ = _kf_2d_scan(12, 12, 4, prune_log_weight=1e9)
    assert len(pruned.active) < len(kept.active) == 18
    for layer in ("prior_um", "smoothed_um"):
        pruned_mae = _mae(getattr(pruned_map, layer), truth_um)
        assert pruned_mae == pytest.approx(_mae(getattr(kept_map, layer), truth_um), rel=0.03)


def test_the_smoother_in_column_blocks_stays_close_to_the_whole_row_smoother() -> None:
    _, blocks, truth_um = _kf_2d_scan(6, 30, 6, smooth_block_cols=8, smooth_margin_cols=8)
    _, whole, _ = _kf_2d_scan(6, 30, 6, smooth_block_cols=30)
    assert not np.array_equal(blocks.smoothed_um, whole.smoothed_um)
    assert _mae(blocks.smoothed_um, truth_um) < 1.05 * _mae(whole.smoothed_um, truth_um)
    np.testing.assert_allclose(blocks.smoothed_sigma_um, whole.smoothed_sigma_um, rtol=0.1)
    np.testing.assert_array_equal(blocks.posterior_um, whole.posterior_um)  # the same scan


def test_an_nshp_support_wider_than_the_slide_is_the_whole_slide_behind() -> None:
    """The support's neighbours are enumerated within the grid: a support of 10^9 on 5x6
    tiles scans as one of 5 (the widest reach there) and at once; it used to enumerate
    10^18 candidates, until the service was killed for its memory."""
    truth_um, measured_um = _maps(5, 6, seed=3)
    settings = default_settings(ScanGrid(5, 6))
    scans = [
        replay(
            registry.create("nshp-wiener0", settings, {"support": support}), truth_um, measured_um
        )
        for support in (5, 10**9)
    ]
    np.testing.assert_array_equal(scans[0].focus_map.prior_um, scans[1].focus_map.prior_um)


def test_a_bank_of_members_each_below_the_smoothers_share_still_has_a_map() -> None:
    """1200 members alike, each of weight 1/1200, are under the smoother's 1/1000 share:
    the smoothed map blended none of them and failed ("operands could not be broadcast")."""
    truth_um, measured_um = _maps(3, 3, seed=2)
    strategy = registry.create(
        "kf-2d",
        default_settings(ScanGrid(3, 3)),
        {"lengths_tiles": [4.0] * 1200, "sigmas_um": [1.0], "tilt_sigmas_um_per_tile": [0.3]},
    )
    run = replay(strategy, truth_um, measured_um)
    assert np.all(np.isfinite(run.focus_map.posterior_um))
