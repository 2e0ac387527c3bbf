"""`gp-oracle`, the benchmarks' floor: exact Gaussian-process regression with the generator's
covariance, served only by the benchmarks' catalogue."""

from __future__ import annotations

import math

import numpy as np
import pytest

from focustrack.bench import strategies
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces, surface_covariance
from focustrack_estimator.replay import replay

NOISE_UM = 1.5


def _maps(rows: int, cols: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    truth_um = generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed)[0]
    noise_um = np.random.default_rng([seed, 7]).normal(0.0, NOISE_UM, truth_um.shape)
    return truth_um, truth_um + noise_um


def test_gp_oracle_equals_direct_gaussian_process_regression() -> None:
    rows, cols = 4, 5
    spec = SurfaceSpec(rows=rows, cols=cols)
    truth_um, measured_um = _maps(rows, cols, seed=3)
    settings = default_settings(ScanGrid(rows, cols), start_z_um=0.5)
    result = replay(strategies.create("gp-oracle", settings), truth_um, measured_um)

    order = settings.grid.serpentine
    r = np.array([t.row for t in order])
    c = np.array([t.col for t in order])
    K = surface_covariance(spec, r, c)
    z = measured_um[r, c] - 0.5
    for i, tile in enumerate(order):
        if i == 0:
            mean, var = 0.0, K[0, 0]
        else:
            A = K[:i, :i] + NOISE_UM**2 * np.eye(i)
            mean = K[i, :i] @ np.linalg.solve(A, z[:i])
            var = K[i, i] - K[i, :i] @ np.linalg.solve(A, K[:i, i])
        assert result.focus_map.prior_um[tile.row, tile.col] == pytest.approx(mean + 0.5, abs=1e-9)
        assert result.focus_map.prior_sigma_um[tile.row, tile.col] == pytest.approx(
            math.sqrt(var), abs=1e-9
        )
    A = K + NOISE_UM**2 * np.eye(len(z))
    final = 0.5 + K @ np.linalg.solve(A, z)
    np.testing.assert_allclose(result.focus_map.posterior_um[r, c], final, atol=1e-9)


def test_gp_oracle_rejects_a_spec_of_another_size() -> None:
    with pytest.raises(ValueError, match="grid"):
        strategies.create("gp-oracle", default_settings(ScanGrid(4, 4)), {"rows": 20, "cols": 20})
