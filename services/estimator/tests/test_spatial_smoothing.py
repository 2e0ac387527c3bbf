"""RTS smoothing of kf-2d: the smoothed layers of the 2-D estimator's focus map."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import SlideSettings
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry, row_model
from focustrack_estimator.replay import replay, simulated_measurement
from focustrack_estimator.row_model import RowModel, matern32, smooth_member

NOISE_UM = 1.5


def _measured(truth_um: np.ndarray, seed: int) -> np.ndarray:
    return truth_um + np.random.default_rng([seed, 7]).normal(0.0, NOISE_UM, truth_um.shape)


def test_one_member_smoother_is_gaussian_process_regression_on_all_measurements() -> None:
    """With one model the smoothed map is the GP posterior of that model given every tile."""
    rows, cols, sigma_um, length, tilt, start_um = 5, 4, 1.4, 6.0, 0.3, 0.5
    truth_um = generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed=4)[0]
    measured_um = _measured(truth_um, seed=4)
    settings = default_settings(ScanGrid(rows, cols), start_z_um=start_um)
    bank = {"sigmas_um": [sigma_um], "lengths_tiles": [length], "tilt_sigmas_um_per_tile": [tilt]}
    strategy = registry.create("kf-2d", settings, bank)
    fm = replay(strategy, truth_um, measured_um).focus_map

    r, c = (a.ravel() for a in np.mgrid[:rows, :cols])
    plane = np.stack([np.ones(r.size), c - (cols - 1) / 2.0, r - (rows - 1) / 2.0], axis=1)
    plane_var = np.diag([settings.start_sigma_um**2, tilt**2, tilt**2])
    K = plane @ plane_var @ plane.T
    K += sigma_um**2 * matern32(r[:, None] - r, length) * matern32(c[:, None] - c, length)
    A = K + NOISE_UM**2 * np.eye(r.size)
    mean_um = start_um + K @ np.linalg.solve(A, measured_um.ravel() - start_um)
    var_um2 = np.diag(K - K @ np.linalg.solve(A, K))
    np.testing.assert_allclose(fm.smoothed_um.ravel(), mean_um, atol=1e-7)
    np.testing.assert_allclose(fm.smoothed_sigma_um.ravel() ** 2, var_um2, atol=1e-7)
    last = settings.grid.serpentine[-1]  # the smoother ends where the filter ends
    assert fm.smoothed_um[last.row, last.col] == pytest.approx(fm.posterior_um[last.row, last.col])


def test_smoothing_improves_the_final_map_and_its_sigma_matches_the_error() -> None:
    size = 12
    filtered_mae, smoothed_mae, z_scores = [], [], []
    for seed, truth_um in enumerate(generate_surfaces(SurfaceSpec(rows=size, cols=size), 3, 21)):
        strategy = registry.create(
            "kf-2d", default_settings(ScanGrid(size, size), noise_sigma_um=NOISE_UM)
        )
        fm = replay(strategy, truth_um, _measured(truth_um, seed)).focus_map
        assert np.mean(fm.smoothed_sigma_um) < 0.9 * np.mean(fm.posterior_sigma_um)
        filtered_mae.append(np.mean(np.abs(fm.posterior_um - truth_um)))
        smoothed_mae.append(np.mean(np.abs(fm.smoothed_um - truth_um)))
        z_scores.append(((fm.smoothed_um - truth_um) / fm.smoothed_sigma_um).ravel())
    assert np.mean(smoothed_mae) < 0.85 * np.mean(filtered_mae)
    z = np.concatenate(z_scores)
    # A consistent sigma: errors of unit variance in sigmas, about 95% within two sigmas.
    assert 0.6 < np.mean(z**2) < 1.6
    assert 0.88 < np.mean(np.abs(z) < 2.0) < 0.99


def test_smoothed_layers_cover_the_tiles_finished_so_far() -> None:
    rows, cols = 4, 5
    truth_um = generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed=8)[0]
    measured_um = _measured(truth_um, seed=8)
    settings = default_settings(ScanGrid(rows, cols))
    strategy = registry.create("kf-2d", settings)
    assert strategy.focus_map().smoothed_um is None  # nothing finished yet
    while np.isfinite(strategy.map.posterior_um).sum() < cols + 2:  # row 0, 2 tiles of row 1
        acquisition = strategy.next_acquisition()
        measured = measured_um[acquisition.row, acquisition.col]
        strategy.record(acquisition, simulated_measurement(acquisition, measured))
    mid = strategy.focus_map()
    np.testing.assert_array_equal(np.isfinite(mid.smoothed_um), np.isfinite(mid.posterior_um))
    assert np.isfinite(mid.smoothed_um).sum() == cols + 2
    # Row 0 learns from row 1; the newest tile is the last step, so smoothed = filtered.
    assert not np.allclose(mid.smoothed_um[0], mid.posterior_um[0])
    newest = settings.grid.serpentine[cols + 1]
    assert mid.smoothed_um[newest.row, newest.col] == pytest.approx(
        mid.posterior_um[newest.row, newest.col]
    )
    # Asking for the map mid-scan changes nothing in the scan.
    final = replay(strategy, truth_um, measured_um).focus_map
    untouched = replay(registry.create("kf-2d", settings), truth_um, measured_um).focus_map
    np.testing.assert_array_equal(final.smoothed_um, untouched.smoothed_um)
    np.testing.assert_array_equal(final.posterior_um, untouched.posterior_um)


def _gp_posterior(
    settings: SlideSettings, model: RowModel, z_um: np.ndarray, R_um2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The GP posterior mean and variance of every tile given the finite `z_um` (direct solve)."""
    rows, cols = z_um.shape
    r, c = (a.ravel() for a in np.mgrid[:rows, :cols])
    plane = np.stack([np.ones(r.size), c - (cols - 1) / 2.0, r - (rows - 1) / 2.0], axis=1)
    tilt_var = model.tilt_sigma_um_per_tile**2
    K = plane @ np.diag([settings.start_sigma_um**2, tilt_var, tilt_var]) @ plane.T
    K += (
        model.sigma_um**2
        * matern32(r[:, None] - r, model.length_tiles)
        * matern32(c[:, None] - c, model.length_tiles)
    )
    seen = np.isfinite(z_um.ravel())
    A = K[np.ix_(seen, seen)] + np.diag(R_um2.ravel()[seen])
    Ks = K[:, seen]
    mean_um = settings.start_z_um + Ks @ np.linalg.solve(
        A, z_um.ravel()[seen] - settings.start_z_um
    )
    var_um2 = np.diag(K - Ks @ np.linalg.solve(A, Ks.T))
    return mean_um.reshape(rows, cols), var_um2.reshape(rows, cols)


def test_the_smoother_skips_tiles_without_a_measurement_exactly() -> None:
    """Tiles given up (NaN) have a zero measurement row in the batch update: the one-window
    smoother is still the GP posterior given the measured tiles, at every tile."""
    rows, cols = 6, 5
    settings = default_settings(ScanGrid(rows, cols), start_z_um=0.3)
    model = RowModel(1.4, 6.0, 0.3, cols)
    z_um = _measured(generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed=5)[0], seed=5)
    R_um2 = np.random.default_rng(5).uniform(1.0, 3.0, z_um.shape)
    z_um[1, 2] = z_um[4, 0] = z_um[4, 1] = np.nan
    mean_um, var_um2 = smooth_member(model, settings, z_um, R_um2, block_cols=8, margin_cols=8)
    expected_mean_um, expected_var_um2 = _gp_posterior(settings, model, z_um, R_um2)
    np.testing.assert_allclose(mean_um, expected_mean_um, atol=1e-7)
    np.testing.assert_allclose(var_um2, expected_var_um2, atol=1e-7)


def test_the_smoother_gives_the_same_map_whatever_the_batch_of_blocks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rows, cols = 5, 30
    settings = default_settings(ScanGrid(rows, cols))
    model = RowModel(1.4, 6.0, 0.3, cols)
    z_um = _measured(generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed=6)[0], seed=6)
    R_um2 = np.full(z_um.shape, NOISE_UM**2)
    batched = smooth_member(model, settings, z_um, R_um2, block_cols=4, margin_cols=4)
    monkeypatch.setattr(row_model, "SMOOTH_BATCH_BLOCKS", 1)
    one_by_one = smooth_member(model, settings, z_um, R_um2, block_cols=4, margin_cols=4)
    for got, expected in zip(batched, one_by_one, strict=True):
        assert np.isfinite(got).all()
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
