"""`gp-oracle`: the floor every estimator is measured against, for the benchmarks only.

Gaussian-process regression with the generator's exact covariance
(`focustrack_core.surfaces.surface_covariance`) is the Bayes-optimal
linear estimator of a generated map; no scanner knows that covariance, so the
oracle is a benchmark's reference, never served by the estimator. It walks the
serpentine as every 2-D estimator does (`SerpentineFilter`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
from pydantic import Field

from focustrack_core.domain import SlideSettings
from focustrack_core.geometry import Tile
from focustrack_core.surfaces import SurfaceSpec, surface_covariance
from focustrack_estimator.filter_params import RetryParams
from focustrack_estimator.serpentine import Gaussian, SerpentineFilter
from focustrack_estimator.strategy import NOMINAL_FLOPS_PER_S, Cost, StrategyEntry, tile_cost

_SPEC = SurfaceSpec()


class GpOracle(SerpentineFilter):
    """Gaussian-process regression with the generator's exact covariance (not for scanners).

    The prior of each tile is the GP posterior given every earlier measurement;
    once the scan is complete the map (posterior) is the GP posterior given all
    of them. The mean is `settings.start_z_um` (the generator's is zero). The
    Cholesky factor of the measured tiles' covariance (plus their R) grows by
    one row per measurement, so each prior costs one triangular solve.
    """

    name = "gp-oracle"

    def __init__(self, settings: SlideSettings, spec: SurfaceSpec, params: RetryParams) -> None:
        super().__init__(settings, params)
        if (spec.rows, spec.cols) != self.grid.shape:
            raise ValueError(f"surface spec is {spec.rows}x{spec.cols}, grid is {self.grid.shape}")
        rows, cols = np.divmod(np.arange(self.grid.n_tiles), self.grid.cols)
        self._K = surface_covariance(spec, rows, cols)  # (n_tiles, n_tiles), flat index r*cols+c
        self._observed: list[int] = []  # flat indices of measured tiles, in measurement order
        self._L = np.zeros_like(self._K)  # Cholesky factor of K[obs, obs] + diag(R)
        self._white = np.zeros(self.grid.n_tiles)  # L^-1 (z_obs - mean)
        self._cross = np.zeros(0)  # L^-1 K[obs, tile] of the current tile

    def _flat(self, tile: Tile) -> int:
        return tile.row * self.grid.cols + tile.col

    def _predict(self, tile: Tile) -> Gaussian:
        t, k = self._flat(tile), len(self._observed)
        self._cross = scipy.linalg.solve_triangular(
            self._L[:k, :k], self._K[self._observed, t], lower=True
        )
        mean = self.settings.start_z_um + self._cross @ self._white[:k]
        return Gaussian(float(mean), float(self._K[t, t] - self._cross @ self._cross))

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        if z_um is None:
            return prior
        k, innovation_var = len(self._observed), prior.var_um2 + R_um2
        self._L[k, :k] = self._cross
        self._L[k, k] = math.sqrt(innovation_var)
        self._white[k] = (z_um - prior.mean_um) / self._L[k, k]
        self._observed.append(self._flat(tile))
        gain = prior.var_um2 / innovation_var
        return Gaussian(prior.mean_um + gain * (z_um - prior.mean_um), prior.var_um2 * (1.0 - gain))

    def _finish(self) -> None:
        """The final map: every tile's GP posterior given all measurements."""
        k = len(self._observed)
        cross = scipy.linalg.solve_triangular(
            self._L[:k, :k], self._K[self._observed, :], lower=True
        )  # (k, n_tiles)
        mean = self.settings.start_z_um + cross.T @ self._white[:k]
        var = np.diag(self._K) - np.sum(cross**2, axis=0)
        self.map.posterior_um = mean.reshape(self.grid.shape)
        self.map.posterior_sigma_um = np.sqrt(np.clip(var, 0.0, None)).reshape(self.grid.shape)


class GpOracleParams(RetryParams):
    """gp-oracle: the `SurfaceSpec` of the maps it is the floor for (benchmarks only)."""

    rows: int | None = Field(None, ge=1, description="The spec's rows (none: the grid's)")
    cols: int | None = Field(None, ge=1, description="The spec's columns (none: the grid's)")
    field_sigma_um: float = Field(_SPEC.field_sigma_um, ge=0.0, description="Field std, um")
    range_tiles: float = Field(
        _SPEC.range_tiles, gt=0.0, description="Field correlation range, tiles"
    )
    tilt_sigma_um_per_tile: float = Field(
        _SPEC.tilt_sigma_um_per_tile, ge=0.0, description="Std of each tilt, um/tile"
    )
    bend_sigma_um: float = Field(_SPEC.bend_sigma_um, ge=0.0, description="Bend std, um")
    step_um: float = Field(
        _SPEC.step_um, description="Height of a step across the slide, um (0: none)"
    )
    smooth_sigma_tiles: float = Field(
        _SPEC.smooth_sigma_tiles, ge=0.0, description="Smoothing of the field, tiles"
    )


def gp_oracle(settings: SlideSettings, params: GpOracleParams) -> GpOracle:
    """The oracle for surfaces of this `SurfaceSpec` (rows, cols: the grid's when None).

    With `step_um` != 0 the surfaces are not Gaussian; the oracle then uses the
    covariance of the Gaussian part only (`surface_covariance`).
    """
    spec = SurfaceSpec(
        rows=settings.grid.rows if params.rows is None else params.rows,
        cols=settings.grid.cols if params.cols is None else params.cols,
        field_sigma_um=params.field_sigma_um,
        range_tiles=params.range_tiles,
        tilt_sigma_um_per_tile=params.tilt_sigma_um_per_tile,
        bend_sigma_um=params.bend_sigma_um,
        step_um=params.step_um,
        smooth_sigma_tiles=params.smooth_sigma_tiles,
    )
    return GpOracle(settings, spec, params)


def gp_oracle_cost(settings: SlideSettings, params: GpOracleParams) -> Cost:
    """The oracle's cost: the tiles' covariance K, its Cholesky factor L and the final map's
    cross terms, each n_tiles^2 floats (90x90: 1.6 GB; 500x500: 1.4 TB); a prior is a
    triangular solve against up to n_tiles measured tiles."""
    n_tiles = settings.grid.n_tiles
    return tile_cost(settings) + Cost(3 * 8 * n_tiles**2, n_tiles**2 / NOMINAL_FLOPS_PER_S)


GP_ORACLE = StrategyEntry(GpOracleParams, gp_oracle, gp_oracle_cost)
