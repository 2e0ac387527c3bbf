"""2-D estimators: use the row above, not only the path behind (docs/spatial.md).

In a serpentine scan the tile above the current one was measured a whole row
ago; a 1-D filter along the path has mostly forgotten it. The strategies here
carry the previous row(s) in their state:

- `nshp-wiener0`, `nshp-wiener1` (`NshpFilter`): the thesis' Non-Symmetric
  Half-Plane filter (ch. 4, eq. 4-1 to 4-4, Algorithm 3) with the two causes of
  its failure (section 4-2-4) removed. The state holds heights only, so the
  y-gradient is implied by measured heights instead of carried as a state that
  is never observed; and the state's every element is corrected with the full
  Kalman gain and propagated with its full covariance, so the prediction uses
  the neighbours' estimates with their correct (cross-)covariances rather than
  as if they were noise-free inputs (no "K[slc] = 0", Algorithm 3 line 13).
- `kf-2d` (`RowBankFilter`): a strip processor (Woods and Radewan's term)
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
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg

from focustrack_core.domain import FocusMap
from focustrack_core.geometry import Tile
from focustrack_estimator.bank import mixture
from focustrack_estimator.kalman_strategies import rts_smooth
from focustrack_estimator.serpentine import FilterOptions, Gaussian, SerpentineFilter
from focustrack_estimator.sqrt_filter import SqrtKalmanFilter, psd_factor
from focustrack_estimator.strategy import SlideSettings, Strategy

# --- NSHP ------------------------------------------------------------------------------


def nshp_weights(offsets: np.ndarray, order: int) -> np.ndarray:
    """Prediction weights of the support heights for the tile at offset (0, 0).

    `offsets` (n, 2) holds each support tile's (d_row, d_col) from the predicted
    tile. Order 0: the inverse-distance weighted mean of the support heights
    (the thesis' weights, section 4-1). Order 1: the inverse-distance weighted
    least-squares plane through them, evaluated at the tile, so the local
    x- and y-slopes come from measured heights (where the support spans only
    one row or column, that direction's slope is left out). Weights sum to one.
    """
    if order not in (0, 1):
        raise ValueError(f"NSHP order must be 0 or 1, got {order}")
    inverse_distance = 1.0 / np.hypot(offsets[:, 0], offsets[:, 1])
    columns = [np.ones(len(offsets))]
    if order == 1:
        columns += [offsets[:, k] for k in (0, 1) if np.ptp(offsets[:, k]) > 0]
    X = np.stack(columns, axis=1)
    if np.linalg.matrix_rank(X) < X.shape[1]:
        X = X[:, :1]
    XtW = X.T * inverse_distance
    # weights w with w @ heights = e0' (X' W X)^-1 X' W heights (the fitted plane at (0, 0))
    return np.linalg.solve(XtW @ X, XtW)[0]


class NshpFilter(SerpentineFilter):
    """The NSHP Kalman filter over heights (thesis ch. 4), with the full-state correction.

    State: the heights of the tiles of the current row and the `support` rows
    above (those a later tile's support can still reach). Each step appends the
    new tile with the support prediction height = sum(w * neighbours) + noise of
    variance `q_um2` (eq. 4-2 and 4-4, as a growing state instead of a shift
    register) and drops the row no longer reachable. Support (eq. 4-1, fig. 4-2,
    M = `support`): the M tiles behind on the current row, and M rows above from
    M columns back to M columns ahead, mirrored on rows scanned right to left.
    """

    def __init__(
        self,
        settings: SlideSettings,
        *,
        name: str,
        order: int,
        support: int,
        q_um2: float,
        max_retries: int,
    ) -> None:
        super().__init__(settings, FilterOptions(max_retries=max_retries))
        if support < 1 or q_um2 <= 0:
            raise ValueError(f"need support >= 1 and q_um2 > 0, got {support}, {q_um2}")
        self.name = name
        self.order, self.support, self.q_um2 = order, support, q_um2
        self._tiles: list[Tile] = []  # the tile of each state element
        self._kf = SqrtKalmanFilter(dim_x=1, dim_z=1)

    def _support(self, tile: Tile) -> list[Tile]:
        """The already-scanned NSHP neighbours of `tile` (eq. 4-1 with M1 = M2 = M)."""
        M = self.support
        behind = -1 if tile.row % 2 == 0 else 1  # serpentine: even rows go left to right
        candidates = [Tile(tile.row, tile.col + behind * k) for k in range(1, M + 1)]
        candidates += [
            Tile(tile.row - k, tile.col + d) for k in range(1, M + 1) for d in range(-M, M + 1)
        ]
        return [t for t in candidates if self.grid.contains(t.row, t.col)]

    def _predict(self, tile: Tile) -> Gaussian:
        if not self._tiles:
            self._kf.x = np.array([[self.settings.start_z_um]])
            self._kf.P = np.array([[self.settings.start_sigma_um**2]])
        else:
            index = {t: i for i, t in enumerate(self._tiles)}
            support = self._support(tile)
            kept = [i for i, t in enumerate(self._tiles) if t.row >= tile.row - self.support]
            offsets = np.array([(t.row - tile.row, t.col - tile.col) for t in support], float)
            F = np.zeros((len(kept) + 1, len(self._tiles)))
            F[np.arange(len(kept)), kept] = 1.0
            F[-1, [index[t] for t in support]] = nshp_weights(offsets, self.order)
            Q_sqrt = np.zeros((len(kept) + 1, 1))  # noise enters the new tile only
            Q_sqrt[-1, 0] = math.sqrt(self.q_um2)
            self._kf.predict(F=F, Q_sqrt=Q_sqrt)
            self._tiles = [self._tiles[i] for i in kept]
        self._tiles.append(tile)
        return Gaussian(self._kf.x[-1, 0], float(np.sum(self._kf.P_sqrt[-1] ** 2)))

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        if z_um is None:
            return prior
        H = np.zeros((1, len(self._tiles)))
        H[0, -1] = 1.0
        # Full gain on every element (the thesis zeroed it outside the support): the rows
        # above are corrected by this tile too, as the joint Gaussian requires.
        self._kf.update(z_um, R=R_um2, H=H)
        return Gaussian(self._kf.x[-1, 0], float(np.sum(self._kf.P_sqrt[-1] ** 2)))


# --- kf-2d: a bank of row-state (strip) filters ------------------------------------------


#: State elements of the plane in `RowModel`: offset (um), tilt along x and y (um/tile).
N_PLANE = 3


def matern32(distance: np.ndarray, length: float) -> np.ndarray:
    """Matern-3/2 correlation at `distance` for length scale `length` (same units)."""
    a = math.sqrt(3.0) * np.abs(distance) / length
    return (1.0 + a) * np.exp(-a)


@dataclass(frozen=True)
class RowModel:
    """A separable Gaussian field sigma^2 k(dy) k(dx), Matern-3/2 in both, plus a plane.

    As a state-space model over rows (a strip processor): the state is
    [offset, tilt_x, tilt_y, (f, df/dy) of column 0, (f, df/dy) of column 1, ...]
    (the plane's three coefficients are constant over the slide); from one row
    to the next each column's (f, df/dy) follows the exact discretisation of the
    Matern-3/2 stochastic differential equation (a 2-state Markov process in y),
    with process noise correlated across columns by k(dx). The filter over this
    state is exact Gaussian-process regression for the separable covariance
    plus a plane with a Gaussian prior (universal kriging when that prior is vague).
    """

    sigma_um: float
    length_tiles: float
    tilt_sigma_um_per_tile: float  # prior std of each tilt coefficient
    cols: int

    @cached_property
    def _lam(self) -> float:
        return math.sqrt(3.0) / self.length_tiles

    @cached_property
    def _column_corr(self) -> np.ndarray:
        c = np.arange(self.cols)
        return matern32(c[:, None] - c[None, :], self.length_tiles)

    @cached_property
    def _stationary_y(self) -> np.ndarray:
        """Stationary covariance of (f, df/dy) of one column per unit sigma^2."""
        return np.diag([1.0, self._lam**2])

    @cached_property
    def _step_y(self) -> np.ndarray:
        """exp(A) of the Matern-3/2 SDE matrix A = [[0, 1], [-lam^2, -2 lam]] (one row)."""
        lam = self._lam
        return math.exp(-lam) * np.array([[1.0 + lam, 1.0], [-(lam**2), 1.0 - lam]])

    @cached_property
    def F(self) -> np.ndarray:  # noqa: N802 (the equations' names)
        """Row-to-row transition, (N_PLANE + 2 cols) square."""
        return scipy.linalg.block_diag(np.eye(N_PLANE), np.kron(np.eye(self.cols), self._step_y))

    @cached_property
    def Q(self) -> np.ndarray:  # noqa: N802 (the equations' names)
        """Row-to-row process noise (um^2): stationary minus propagated, correlated across x."""
        A, P = self._step_y, self._stationary_y
        noise_y = P - A @ P @ A.T
        field = self.sigma_um**2 * np.kron(self._column_corr, noise_y)
        return scipy.linalg.block_diag(np.zeros((N_PLANE, N_PLANE)), field)

    @cached_property
    def Q_sqrt(self) -> np.ndarray:  # noqa: N802 (the equations' names)
        """A factor of Q, computed once (Q is rank-deficient: the plane has no noise)."""
        return psd_factor(self.Q)

    def initial(self, offset_sigma_um: float) -> np.ndarray:
        """Covariance of the first row's state: the plane and the stationary field."""
        tilt_var = self.tilt_sigma_um_per_tile**2
        plane = np.diag([offset_sigma_um**2, tilt_var, tilt_var])
        field = self.sigma_um**2 * np.kron(self._column_corr, self._stationary_y)
        return scipy.linalg.block_diag(plane, field)


class RowBankFilter(SerpentineFilter):
    """`kf-2d`: strip filters for every (sigma, length, tilt) of a grid, averaged by likelihood.

    Member i's weight is proportional to the likelihood of all innovations so
    far under its model (Bayesian model averaging over fixed models, the
    multiple-model adaptive estimator without switching); the tile's prior and
    posterior are the weighted mixture's mean and variance. `focus_map` adds
    the RTS-smoothed layers (`_smoothed`: `kf-2d-rts` in the benchmark).
    """

    name = "kf-2d"

    def __init__(
        self,
        settings: SlideSettings,
        *,
        sigmas_um: tuple[float, ...],
        lengths_tiles: tuple[float, ...],
        tilt_sigmas_um_per_tile: tuple[float, ...],
        max_retries: int,
    ) -> None:
        super().__init__(settings, FilterOptions(max_retries=max_retries))
        grid_values = (*sigmas_um, *lengths_tiles, *tilt_sigmas_um_per_tile)
        if not (sigmas_um and lengths_tiles and tilt_sigmas_um_per_tile) or min(grid_values) <= 0:
            raise ValueError(
                "the bank's sigmas, lengths and tilt sigmas must be given and positive"
            )
        cols = self.grid.cols
        self.models = [
            RowModel(sigma, length, tilt, cols)
            for sigma in sigmas_um
            for length in lengths_tiles
            for tilt in tilt_sigmas_um_per_tile
        ]
        self._filters = []
        for model in self.models:
            kf = SqrtKalmanFilter(dim_x=N_PLANE + 2 * cols, dim_z=1)
            kf.x[0, 0] = settings.start_z_um
            kf.P = model.initial(settings.start_sigma_um)
            self._filters.append(kf)
        self.log_weights = np.zeros(len(self.models))  # log posterior model probabilities
        self._row = 0
        # For the RTS smoother over rows (`_smoothed`): every member's state after each finished
        # row's last update (the current row's is live; the priors follow from these).
        self._row_posteriors: list[tuple[np.ndarray, np.ndarray]] = []
        self._n_finished = 0  # tiles corrected (with or without a measurement)
        self._smoothed_at = -1  # `_n_finished` when the smoothed layers were last filled

    @property
    def weights(self) -> np.ndarray:
        """Posterior probability of each member model, shape (len(models),)."""
        w = np.exp(self.log_weights - self.log_weights.max())
        return w / w.sum()

    def _design(self, rows: np.ndarray) -> np.ndarray:
        """Measurement rows of every tile of `rows`, shape (len(rows), cols, dim_x).

        A tile's height is the plane at its centre plus its column's field.
        """
        cols = self.grid.cols
        column = np.arange(cols)
        H = np.zeros((len(rows), cols, N_PLANE + 2 * cols))
        H[:, :, 0] = 1.0
        H[:, :, 1] = column - (cols - 1) / 2.0
        H[:, :, 2] = (np.asarray(rows) - (self.grid.rows - 1) / 2.0)[:, None]
        H[:, column, N_PLANE + 2 * column] = 1.0
        return H

    def _h(self, tile: Tile) -> np.ndarray:
        """Measurement row of one tile, shape (1, dim_x) (`_design`)."""
        return self._design(np.array([tile.row]))[0, [tile.col]]

    def _states(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the members' x (n_members, dim_x) and P factors (n_members, dim_x, dim_x)."""
        return (
            np.stack([kf.x[:, 0] for kf in self._filters]),
            np.stack([kf.P_sqrt for kf in self._filters]),
        )

    def _mixture(self, tile: Tile) -> Gaussian:
        H = self._h(tile)
        means = np.array([(H @ kf.x).item() for kf in self._filters])
        variances = np.array([np.sum((H @ kf.P_sqrt) ** 2) for kf in self._filters])
        mean, var = mixture(means, variances, self.weights)
        return Gaussian(float(mean), float(var))

    def _predict(self, tile: Tile) -> Gaussian:
        if tile.row != self._row:  # a new row: propagate every column one row down
            self._row_posteriors.append(self._states())
            for model, kf in zip(self.models, self._filters, strict=True):
                kf.predict(F=model.F, Q_sqrt=model.Q_sqrt)
            self._row = tile.row
        return self._mixture(tile)

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        self._n_finished += 1
        if z_um is None:
            return prior
        H = self._h(tile)
        for i, kf in enumerate(self._filters):
            kf.update(z_um, R=R_um2, H=H)
            self.log_weights[i] += kf.log_likelihood
        self.log_weights -= self.log_weights.max()
        return self._mixture(tile)

    def _smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        """RTS-smoothed heights (um) and variances (um^2) given every measurement so far.

        Both (rows reached, cols). Fixed-interval smoothing over rows: step k is
        row k, its posterior the state after the row's last update (the live
        state for the current row), its prior row k - 1's posterior propagated
        (F x, F P F' + Q: what the filter's predict did; recomputed here rather
        than stored, which halves the memory kept per row). A row's state holds
        every tile of that row, so each tile is read
        from its own row's smoothed state, which has seen the rows below it and
        the rest of its row: for the bank's models that is exactly the GP
        posterior given all measurements. Each member is smoothed and the
        members are blended with their current weights, which for fixed models
        are the model probabilities given every measurement (the exact smoothed
        mixture).
        """
        x_post, S_post = (
            np.array(a) for a in zip(*self._row_posteriors, self._states(), strict=True)
        )  # x (n_rows, n_members, dim_x), S (n_rows, n_members, dim_x, dim_x)
        P_post = S_post @ S_post.swapaxes(-1, -2)
        n_rows = len(x_post)
        H = self._design(np.arange(n_rows))  # (n_rows, cols, dim_x)
        means, variances = [], []
        for m, model in enumerate(self.models):
            x, P, F = x_post[:, m], P_post[:, m], model.F
            # Priors of rows 1..n-1; row 0's (the initial state) is not used by the smoother.
            x_prior = np.concatenate([x[:1], x[:-1] @ F.T])
            P_prior = np.concatenate([P[:1], F @ P[:-1] @ F.T + model.Q])
            Fs = np.broadcast_to(F, (n_rows, *F.shape))
            xs, Ps = rts_smooth(x_prior, P_prior, x, P, Fs)
            means.append(np.einsum("rcd,rd->rc", H, xs))
            variances.append(np.sum((H @ Ps) * H, axis=-1))  # h' P h for every tile
        return mixture(np.array(means), np.array(variances), self.weights)

    def focus_map(self) -> FocusMap:
        """The estimates so far, with the RTS-smoothed layers over the tiles finished so far.

        The backward pass runs here, when the map is asked for (and a tile was
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


# --- factories ---------------------------------------------------------------------------
# Defaults chosen on training seeds 0..9 (docs/spatial.md), never on the reported maps.


def nshp_wiener0(
    settings: SlideSettings, *, support: int = 1, q_um2: float = 0.5, max_retries: int = 3
) -> NshpFilter:
    """NSHP filter, order 0: the weighted mean of the support heights, plus noise."""
    return NshpFilter(
        settings, name="nshp-wiener0", order=0, support=support, q_um2=q_um2,
        max_retries=max_retries,
    )  # fmt: skip


def nshp_wiener1(
    settings: SlideSettings, *, support: int = 2, q_um2: float = 0.03, max_retries: int = 3
) -> NshpFilter:
    """NSHP filter, order 1: the support's weighted plane extrapolated to the tile, plus noise."""
    return NshpFilter(
        settings, name="nshp-wiener1", order=1, support=support, q_um2=q_um2,
        max_retries=max_retries,
    )  # fmt: skip


def kf_2d(
    settings: SlideSettings,
    *,
    sigmas_um: tuple[float, ...] = (0.7, 1.4, 2.8),
    lengths_tiles: tuple[float, ...] = (4.0, 8.0, 16.0),
    tilt_sigmas_um_per_tile: tuple[float, ...] = (0.3, 1.5),
    max_retries: int = 3,
) -> RowBankFilter:
    """The best 2-D estimator: the strip-filter bank, learning the slide's field and tilt.

    The bank is every (sigma, length, tilt sigma) of the three grids: 18 filters.
    """
    return RowBankFilter(
        settings, sigmas_um=tuple(sigmas_um), lengths_tiles=tuple(lengths_tiles),
        tilt_sigmas_um_per_tile=tuple(tilt_sigmas_um_per_tile), max_retries=max_retries,
    )  # fmt: skip


STRATEGIES: dict[str, Callable[..., Strategy]] = {
    "kf-2d": kf_2d,
    "nshp-wiener0": nshp_wiener0,
    "nshp-wiener1": nshp_wiener1,
}
