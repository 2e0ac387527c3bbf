"""2-D estimators: use the row above, not only the path behind (docs/spatial.md).

In a serpentine scan the tile above the current one was measured a whole row
ago; a 1-D filter along the path has mostly forgotten it. The 2-D strategies
carry the previous row(s) in their state: the NSHP filters (`nshp`) and, here,
`kf-2d` (`RowBankFilter`), a strip processor (Woods and Radewan's term)
whose state is a whole row of heights and their y-slopes; row to row the
field evolves as a Matern-3/2 process in y with process noise correlated
across columns, plus a plane (offset and tilts) as constant states, so the
model is a separable Gaussian process that the filter computes exactly. The
field's size and length and the tilt's scale are not assumed: a bank of
such filters over a grid of (sigma, length, tilt) runs in parallel and is
averaged with the posterior probability of each member, from the likelihood
of its innovations (estimated online, per slide). Its focus map carries the
RTS-smoothed layers (a fixed-interval smoother over the rows: `kf-2d-rts`).

The floor they are measured against, `gp-oracle`, needs the simulator's true
covariance, so it lives with the benchmarks (`focustrack.bench.oracle`).

All run the one per-tile loop of every filter strategy
(`serpentine.SerpentineFilter`, shared with the 1-D Kalman filters): the prior
of a tile sets a stack of +/- k innovation sigmas; a stack without a peak is
followed by another (`PeakSearch`) until the search ends, after which the
prior stands; the tile is imaged at the acquired frame nearest the posterior.
Heights are in um, lengths in tiles.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Annotated, Any

import numpy as np
import scipy.linalg
from pydantic import Field, Strict

from focustrack_core.domain import (
    Acquisition,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRange,
)
from focustrack_core.geometry import Tile
from focustrack_estimator.bank import mixture, tempered_weights
from focustrack_estimator.filter_params import RetryParams
from focustrack_estimator.lean import SHORT_FRAMES, mixture_skip_risk, skip_risk
from focustrack_estimator.row_model import N_PLANE, RowModel, smooth_member, step_rows
from focustrack_estimator.serpentine import Gaussian, SerpentineFilter
from focustrack_estimator.strategy import (
    NOMINAL_FLOPS_PER_S,
    Cost,
    StrategyEntry,
    StrategyParams,
    tile_cost,
)
from focustrack_estimator.time_state import (
    N_DRIFT,
    DriftModel,
    RevisitParams,
    elapse,
)

# --- kf-2d: a bank of row-state (strip) filters ------------------------------------------


#: Members whose posterior probability is below this (normalised) are left out of the
#: smoothed map (the others' weights renormalised): each member costs a smoother pass, and
#: a 0.1% share moves the blend by 0.1% of the members' difference.
SMOOTH_MIN_WEIGHT = 1e-3


class RowBankFilter(SerpentineFilter):
    """`kf-2d`: strip filters for every (sigma, length, tilt) of a grid, averaged by likelihood.

    `bank` sets the grids, the reduced update and the smoother; `options` the per-tile
    loop's (`SerpentineFilter`: kf-2d's retries, kf-2d-lean's risk rule too).

    Member i's weight is proportional to the likelihood of all innovations so
    far under its model (Bayesian model averaging over fixed models, the
    multiple-model adaptive estimator without switching); the tile's prior and
    posterior are the weighted mixture's mean and variance. `focus_map` adds
    the smoothed layers (`_smoothed`: `kf-2d-rts` in the benchmark).

    Cost per tile, whatever the slide's width (docs/spatial.md):

    - **Reduced update** (Woods and Radewan 1977): a measurement of column c
      corrects only the plane and the columns within `window_cols` of c; the
      gain of every other state is zero. The covariance is updated for that
      gain exactly (Joseph form, so P stays the true error covariance of the
      reduced estimator): the window's block and its cross-covariance with the
      rest change, the rest does not. Where the window spans the row (slides
      up to 2 `window_cols` + 1 wide) this is the full Kalman filter.
    - **Pruning**: at each new row, members whose log weight has fallen
      `prune_log_weight` below the best are dropped for good (their weight is
      then below e^-prune_log_weight, and fixed models cannot win it back
      quickly); the weights of the others are unchanged.
    - Row to row, F is block diagonal (2x2 per column): F P F' costs O(cols^2)
      once a row, O(cols) per tile.

    The members' states are kept stacked: x (n_members, dim_x) and covariances
    P (n_members, dim_x, dim_x), dim_x = N_PLANE + 2 cols (`n_surface`), plus the
    time state's drift and rate where `options` set one (`time_state`: the drift
    moves on with the scan's clock before each tile's prior, and every measurement
    sees it); `active` holds each row's index into `models`.
    """

    def __init__(
        self, settings: SlideSettings, bank: RowBankParams, options: RetryParams, *, name: str
    ) -> None:
        super().__init__(settings, options)
        self.name = name
        self.window_cols, self.prune_log_weight = bank.window_cols, bank.prune_log_weight
        self.smooth_block_cols = bank.smooth_block_cols
        self.smooth_margin_cols = bank.smooth_margin_cols
        cols = self.grid.cols
        self.models = [
            RowModel(sigma, length, tilt, cols)
            for sigma in bank.sigmas_um
            for length in bank.lengths_tiles
            for tilt in bank.tilt_sigmas_um_per_tile
        ]
        self.active = np.arange(len(self.models))  # members still in the bank
        self.drift = DriftModel.of(options)
        self._state_s = 0.0  # the time the drift states hold at
        timed = options if self.drift is not None and isinstance(options, RevisitParams) else None
        self.revisit_share = timed.revisit_drift_share if timed is not None else 0.0
        self.revisit_max_tiles = timed.revisit_max_tiles if timed is not None else 0
        self._revisited_at = -1  # the serpentine position a revisit was last made before
        self.n_surface = N_PLANE + 2 * cols  # the surface's states; the drift's follow
        initial = [model.initial(settings.start_sigma_um) for model in self.models]
        if self.drift is not None:
            drift_P = self.drift.initial_covariance()
            initial = [scipy.linalg.block_diag(P, drift_P) for P in initial]
        self.x = np.zeros((len(self.models), initial[0].shape[0]))
        self.x[:, 0] = settings.start_z_um
        self.P = np.stack(initial)
        # The drift each tile was finished with (um, 0 before): the smoother's
        # measurements are of the surface, the drift at their time taken off.
        self.tile_drift_um = np.zeros(self.grid.shape)
        self.log_weights = np.zeros(len(self.models))  # log posterior model probabilities
        self._row = 0
        # The accepted measurements (um) and their R (um^2), NaN elsewhere: the smoother
        # recomputes the row states from these instead of keeping every row's covariance.
        self.z_um = np.full(self.grid.shape, np.nan)
        self.R_um2 = np.full(self.grid.shape, np.nan)
        self._n_finished = 0  # tiles corrected (with or without a measurement)
        self._smoothed_at = -1  # `_n_finished` when the smoothed layers were last filled

    @property
    def weights(self) -> np.ndarray:
        """Posterior probability of each active member, shape (len(active),)."""
        return tempered_weights(self.log_weights, 1.0)

    def _h(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """The measurement row of `tile` as its non-zero (indices, values) in the state.

        A tile's height is the plane at its centre (offset, x-tilt times the
        column's distance from the centre, y-tilt likewise) plus its column's field.
        """
        indices = [0, 1, 2, N_PLANE + 2 * tile.col]
        values = [
            1.0,
            tile.col - (self.grid.cols - 1) / 2.0,
            tile.row - (self.grid.rows - 1) / 2.0,
            1.0,
        ]
        if self.drift is not None:  # and the drift since the scan began
            indices.append(self.n_surface)
            values.append(1.0)
        return np.array(indices), np.array(values)

    def drift_um(self) -> tuple[float, float]:
        """The drift since the scan began as the bank sees it now: mean (um), variance (um^2);
        (0, 0) without a time state."""
        if self.drift is None:
            return 0.0, 0.0
        d = self.n_surface
        mean, var = mixture(self.x[:, d], self.P[:, d, d], self.weights)
        return float(mean), float(var)

    def _elapse_to(self, t_s: float) -> None:
        """Move the drift states on to the scan's time `t_s` (no time state: nothing)."""
        if self.drift is not None:
            elapse(self.x, self.P, self.drift, self.n_surface, t_s - self._state_s)
            self._state_s = max(self._state_s, t_s)

    def _members(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """Each active member's prediction of `tile`: means (um) and variances (um^2),
        shapes (len(active),)."""
        indices, values = self._h(tile)
        means = self.x[:, indices] @ values
        variances = np.einsum("i,mij,j->m", values, self.P[:, indices[:, None], indices], values)
        return means, variances

    def _mixture(self, tile: Tile) -> Gaussian:
        mean, var = mixture(*self._members(tile), self.weights)
        return Gaussian(float(mean), float(var))

    def _focus_members(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        """Each active member's prediction of `tile`'s focus, as `_members` (the surface's
        here; `kf-2d-laser` adds the tile's reading to its offset's)."""
        return self._members(tile)

    def _unmeasured_risk(self, tile: Tile, prior: Gaussian) -> float:
        """The risk of imaging `tile` at the bank's mean `prior.mean_um` unmeasured: its
        members' mixture's, weighed by their tempered likelihoods (`lean.mixture_skip_risk`,
        `bank.tempered_weights` at `skip_model_temperature`)."""
        return mixture_skip_risk(
            *self._focus_members(tile),
            tempered_weights(self.log_weights, self.options.skip_model_temperature),
            prior.mean_um,
            self.settings.dof_um,
            self.options.skip_sigma_scale,
        )

    def _predict(self, tile: Tile) -> Gaussian:
        if tile.row != self._row:  # a new row: propagate every column one row down
            self._predict_row()
            self._prune()
            self._row = tile.row
        self._elapse_to(self.clock.arrival_s(self.grid, tile))
        return self._mixture(tile)

    def _predict_row(self) -> None:
        """x <- F x, P <- F P F' + Q for every member (`RowModel.F`, `.Q`), in place."""
        A = np.stack([self.models[i].step_y for i in self.active])  # (m, 2, 2)
        n = self.n_surface  # the drift's states do not move from row to row
        step_rows(self.x[:, :n, None], A)
        step_rows(self.P[:, :n], A)
        step_rows(self.P.transpose(0, 2, 1)[:, :n], A)  # F (F P)' = F P F' (P symmetric)
        for m, i in enumerate(self.active):
            model = self.models[i]
            self.P[m, N_PLANE:n, N_PLANE:n] += model.sigma_um**2 * model.field_noise_per_um2

    def _prune(self) -> None:
        keep = self.log_weights >= self.log_weights.max() - self.prune_log_weight
        if not keep.all():
            self.active, self.log_weights = self.active[keep], self.log_weights[keep]
            self.x, self.P = self.x[keep], self.P[keep]

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        self._n_finished += 1
        self.tile_drift_um[tile.row, tile.col] = self.drift_um()[0]
        if z_um is None:
            return prior
        self.z_um[tile.row, tile.col], self.R_um2[tile.row, tile.col] = z_um, R_um2
        self._update(tile, z_um, R_um2)
        return self._mixture(tile)

    def _update(self, tile: Tile, z_um: float, R_um2: float) -> None:
        """Every member's Kalman update with `z_um` (variance `R_um2`) measured on `tile`."""
        indices, values = self._h(tile)
        u = np.einsum("i,min->mn", values, self.P[:, indices])  # P h' of each member (m, n)
        s = u[:, indices] @ values + R_um2  # innovation variances
        y = z_um - self.x[:, indices] @ values  # innovations
        lo, hi = (
            max(0, tile.col - self.window_cols),
            min(self.grid.cols, tile.col + 1 + self.window_cols),
        )
        # Reduced update: gain u_w / s on the window w (the plane and the columns lo..hi-1),
        # zero elsewhere (o). With that gain the Joseph form gives P_ww - u_w u_w'/s,
        # P_wo - u_w u_o'/s and P_oo unchanged (docs/spatial.md); where the window spans the
        # row, o is empty and this is the full update. In place on slices: no copies of P.
        n = self.n_surface  # the drift's states (after n) are in every window
        window = (
            slice(0, N_PLANE),
            slice(N_PLANE + 2 * lo, N_PLANE + 2 * hi),
            slice(n, n + (N_DRIFT if self.drift is not None else 0)),
        )
        others = (slice(N_PLANE, N_PLANE + 2 * lo), slice(N_PLANE + 2 * hi, n))
        # u u' / s as v v' with v = u / sqrt(s): one outer product per row block, and
        # v_i v_j = v_j v_i exactly, so the update adds no asymmetry to P.
        v = u / np.sqrt(s)[:, None]
        for w in window:
            self.x[:, w] += u[:, w] * (y / s)[:, None]
            self.P[:, w, :] -= v[:, w, None] * v[:, None, :]  # P_ww and P_wo
        for w in window:  # P_ow = P_wo': copied, not recomputed (a strided write)
            for o in others:
                self.P[:, o, w] = self.P[:, w, o].transpose(0, 2, 1)
        self.log_weights -= 0.5 * (np.log(2.0 * math.pi * s) + y**2 / s)
        self.log_weights -= self.log_weights.max()

    # --- revisits: a tile of the row measured again to pin the drift down --------------------

    def _plan(self) -> Acquisition | None:
        return self._revisit() or super()._plan()

    def _revisit(self) -> Acquisition | None:
        """A revisit to make before the next tile's own acquisition, None if none.

        Asked once per tile, before its first stack: where the drift holds at least
        `revisit_share` of the tile's predicted variance, the tile could not be imaged
        unmeasured at the stated risk (`lean.skip_risk`) but could after the revisit (the
        variance the revisit's measurement would leave it, `_variance_after`), the
        measured tile of the row nearest it (within `revisit_max_tiles`) gets a short
        stack at its predicted focus now. Its surface is known from its own measurement, so the
        innovation is mostly the drift since: a cleaner measure of it than the new
        tile's, whose surface is unknown too. Cost-aware: a revisit (a stage move there
        and back, 3 frames) is made only where it lets the tile, and the tiles after it
        whose uncertainty is the drift's, be imaged unmeasured.
        """
        risk = self.options.risk_out_of_focus
        position = self._position
        if not (self.revisit_share and risk) or position in (self._revisited_at, self.grid.n_tiles):
            return None
        if self._planes is not None or self._search or self._centre_um is not None:
            return None
        tile = self.grid.serpentine[position]
        prior = self._predict(tile)  # moves the state onto the tile; again in _plan: a no-op
        dof_um, sigma_scale = self.settings.dof_um, self.options.skip_sigma_scale
        if self.drift_um()[1] < self.revisit_share * prior.var_um2 or (
            self._unmeasured_risk(tile, prior) <= risk
        ):
            return None
        measured = np.flatnonzero(np.isfinite(self.z_um[tile.row]))
        near = measured[np.abs(measured - tile.col) <= self.revisit_max_tiles]
        if near.size == 0:
            return None
        target = Tile(tile.row, int(near[np.argmin(np.abs(near - tile.col))]))
        after_um2 = self._variance_after(tile, target, self.expected_r_um2)
        if skip_risk(math.sqrt(after_um2), dof_um, sigma_scale) > risk:
            return None
        self._revisited_at = position
        self._elapse_to(self.clock.arrival_s(self.grid, target))
        predicted = self._mixture(target)
        z = ZRange.centred(predicted.mean_um, SHORT_FRAMES, self.settings.policy.z_step_um)
        return self._acquisition(
            target.row,
            target.col,
            z,
            Purpose.REVISIT,
            measure=True,
            predicted_um=predicted.mean_um,
            predicted_sigma_um=predicted.sigma_um,
        )

    def _variance_after(self, tile: Tile, target: Tile, R_um2: float) -> float:
        """The variance of `tile`'s prediction (um^2) once `target` is measured (variance
        `R_um2`): each member's h P h' - (h P g')^2 / (g P g' + R), mixed by weight."""
        (i, a), (j, b) = self._h(tile), self._h(target)
        cross = np.einsum("i,mij,j->m", a, self.P[:, i[:, None], j], b)
        target_var = np.einsum("i,mij,j->m", b, self.P[:, j[:, None], j], b) + R_um2
        tile_var = np.einsum("i,mij,j->m", a, self.P[:, i[:, None], i], a)
        means = self.x[:, i] @ a
        _, var = mixture(means, np.maximum(tile_var - cross**2 / target_var, 0.0), self.weights)
        return float(var)

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        if acquisition.purpose != Purpose.REVISIT:
            return super()._take(acquisition, measurement)
        tile = Tile(acquisition.row, acquisition.col)
        self.clock.advance(self.grid, tile, acquisition.z.n_frames)
        outcome = Outcome(
            tile.row, tile.col, accepted=False, prior_um=acquisition.predicted_um,
            prior_sigma_um=acquisition.predicted_sigma_um,
        )  # fmt: skip
        if measurement.z_um is None or not measurement.is_observation:
            return outcome  # no peak in 3 frames: the drift is left as it was
        predicted = self._mixture(tile)
        R_um2 = self.default_r_um2 if measurement.sigma_um is None else measurement.sigma_um**2
        innovation_um = measurement.z_um - predicted.mean_um
        self._update(tile, measurement.z_um, R_um2)
        nis = innovation_um**2 / (predicted.var_um2 + R_um2)
        return replace(outcome, accepted=True, innovation_um=innovation_um, nis=nis)

    def _smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        """Smoothed heights (um) and variances (um^2) given every measurement so far.

        Both (rows reached, cols). Each member with a weight of at least
        `SMOOTH_MIN_WEIGHT` is smoothed by `smooth_member` (a fixed-interval
        smoother over rows, column block by column block) and the members are
        blended with their current weights, which for fixed models are the
        model probabilities given every measurement (the exact smoothed mixture).
        With a time state, the smoother reads each measurement less the drift its tile
        was finished with, and adds that drift back to the tile's smoothed surface (the
        focus when it was imaged); the drift's own uncertainty is not in the variances.
        """
        weights = self.weights
        # the best are always kept: in a bank of over 1 / SMOOTH_MIN_WEIGHT members of like
        # weight every one is below it, and the blend of none failed
        kept = weights >= min(SMOOTH_MIN_WEIGHT, weights.max())
        reached = self._row + 1
        drift_um = self.tile_drift_um[:reached]
        smoothed = [
            smooth_member(
                self.models[i],
                self.settings,
                self.z_um[:reached] - drift_um,
                self.R_um2[:reached],
                block_cols=self.smooth_block_cols,
                margin_cols=self.smooth_margin_cols,
            )
            for i in self.active[kept]
        ]
        means = np.array([mean for mean, _ in smoothed]) + drift_um
        variances = np.array([var for _, var in smoothed])
        return mixture(means, variances, weights[kept] / weights[kept].sum())

    def focus_map(self) -> FocusMap:
        """The estimates so far, with the smoothed layers over the tiles finished so far.

        The smoother runs here, when the map is asked for (and a tile was
        finished since the last time), never per measurement.
        """
        if self._n_finished and self._smoothed_at != self._n_finished:
            mean_um, var_um2 = self._smoothed()
            reached = len(mean_um)
            finished = np.isfinite(self.map.posterior_um[:reached])
            self.map.smoothed_um = np.full(self.grid.shape, np.nan)
            self.map.smoothed_sigma_um = np.full(self.grid.shape, np.nan)
            self.map.smoothed_um[:reached] = np.where(finished, mean_um, np.nan)
            self.map.smoothed_sigma_um[:reached] = np.where(
                finished, np.sqrt(np.clip(var_um2, 0.0, None)), np.nan
            )
            self._smoothed_at = self._n_finished
        return self.map


# --- kf-2d's parameters, factory and cost model ---------------------------------------------
# Defaults chosen on training seeds 0..9 (docs/spatial.md), never on the reported maps.

#: The largest value of a bank's grid (a field std in um, a length in tiles, a tilt in
#: um/tile): beyond any slide (1 cm), and where the filter's arithmetic starts to lose its
#: digits (a length of 1e6 tiles smoothed a 30x30 map to 1e4 um; 1e8 um/tile of tilt
#: failed the bank's weights).
BANK_VALUE_MAX = 1e4

#: A bank's grid of one quantity: at least one value, each positive, at most `BANK_VALUE_MAX`.
BankGrid = Annotated[
    tuple[Annotated[float, Field(gt=0.0, le=BANK_VALUE_MAX)], ...],
    Strict(False),
    Field(min_length=1),
]


class RowBankParams(StrategyParams):
    """The strip-filter bank of `kf-2d`: its grids, its reduced update and its smoother."""

    sigmas_um: BankGrid = Field(
        (0.7, 1.4, 2.8), description="The members' field std, um (one member per combination)"
    )
    lengths_tiles: BankGrid = Field(
        (4.0, 8.0, 16.0), description="The members' Matern-3/2 length scale, tiles"
    )
    tilt_sigmas_um_per_tile: BankGrid = Field(
        (0.3, 1.5), description="The members' prior std of each tilt of the plane, um/tile"
    )
    window_cols: int = Field(
        12,
        ge=1,
        description="A measurement corrects the columns within this many of its own (the "
        "reduced update), columns",
    )
    prune_log_weight: float = Field(
        20.0,
        gt=0.0,
        description="Members this far below the best in log likelihood leave the bank",
    )
    smooth_block_cols: int = Field(
        16, ge=1, description="Columns of each block the smoother reads, columns"
    )
    smooth_margin_cols: int = Field(
        8, ge=0, description="Columns on each side of a block the smoother also filters, columns"
    )


class Kf2dParams(RowBankParams, RetryParams, RevisitParams):
    """kf-2d: the strip-filter bank, learning the slide's field and tilt (docs/spatial.md),
    and with a time state the instrument's drift (`time_state`)."""


def kf_2d(settings: SlideSettings, params: Kf2dParams) -> RowBankFilter:
    """The best 2-D estimator: the strip-filter bank, learning the slide's field and tilt.

    The bank is every (sigma, length, tilt sigma) of the three grids: 18 filters by default.
    """
    return RowBankFilter(settings, params, params, name="kf-2d")


# Cost models are fitted to tracemalloc's peak over a scan (tests/test_estimator_budget.py
# keeps them within a factor of the measurement); times are counted operations at
# NOMINAL_FLOPS_PER_S (the budget: focustrack_estimator.budget.Budget).

#: Peak bytes of a kf-2d member per element of its (dim x dim) covariance: P itself, the
#: copies and temporaries of the row prediction, and its model's cached column
#: correlation and process noise (together about as large as P again).
KF2D_PEAK_FLOATS_PER_P_ELEMENT = 5.0


def kf_2d_cost(settings: SlideSettings, bank: RowBankParams) -> Cost:
    """kf-2d: every member keeps a (3 + 2 cols)^2 covariance; a tile's update touches its
    window's rows of it, a new row all of it (F P F'); the smoother works on column blocks."""
    rows, cols = settings.grid.shape
    n_members = len(bank.sigmas_um) * len(bank.lengths_tiles) * len(bank.tilt_sigmas_um_per_tile)
    dim = N_PLANE + 2 * cols
    window_rows = N_PLANE + 2 * min(cols, 2 * bank.window_cols + 1)
    block_dim = N_PLANE + 2 * min(cols, bank.smooth_block_cols + 2 * bank.smooth_margin_cols)
    state_bytes = n_members * dim * dim * 8 * KF2D_PEAK_FLOATS_PER_P_ELEMENT
    smoother_bytes = 8 * (6 * rows * block_dim**2 + 2 * n_members * rows * cols)
    flops_per_tile = n_members * dim * (6 * window_rows + 10 * dim / cols)
    return tile_cost(settings) + Cost(
        int(state_bytes + smoother_bytes), flops_per_tile / NOMINAL_FLOPS_PER_S
    )


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "kf-2d": StrategyEntry(Kf2dParams, kf_2d, kf_2d_cost),
}
