"""Kalman-filter scan strategies: predict the next tile's focus, stack narrowly around it, learn.

Two layers:

- `PathEstimator`: the height along the serpentine path, as a Kalman filter
  sees it: `predict(step)`, `update(z, R)`, `skip()` (a tile left without a
  measurement), `inflate(var)` and `smoothed()`. `PathFilter` is one
  `StateSpaceModel` under a FilterPy `KalmanFilter` (or, with `sqrt=True`, the
  QR square-root filter of `sqrt_filter`); `bank.ModelBank` blends several.
  Each keeps, per finished tile, the prior and posterior state and the F of the
  step onto the tile: what the Rauch-Tung-Striebel smoother needs.
- `KalmanStrategy`: any estimator inside the one per-tile loop every filter
  strategy runs (`serpentine.SerpentineFilter`: the stack around the
  prediction, the search after a stack without a peak, the NIS gate and the
  adaptive R of docs/estimators.md). On each tile the estimator predicts once
  with the model's F and Q for the step that led there; a measurement updates
  it; a tile left without one is skipped.

Strategies are deterministic functions of the measurements they are given, so
replaying a slide's measurement log rebuilds the same filter.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Annotated, Any

import numpy as np
import scipy.linalg
from filterpy.kalman import KalmanFilter
from pydantic import AfterValidator, Field

from focustrack_core.domain import FocusMap, SlideSettings
from focustrack_core.geometry import Step, Tile
from focustrack_estimator.filter_params import FilterParams
from focustrack_estimator.models import (
    DirectionAwareModel,
    GaussMarkovModel,
    StateSpaceModel,
    Transition,
    WienerModel,
    gauss_markov_process_noise,
)
from focustrack_estimator.serpentine import Gaussian, SerpentineFilter
from focustrack_estimator.sqrt_filter import SqrtKalmanFilter
from focustrack_estimator.strategy import (
    Cost,
    CostModel,
    StrategyEntry,
    StrategyParams,
    tile_cost,
)
from focustrack_estimator.time_state import N_DRIFT, DriftModel, TimeStateParams


def rts_gains(FP: np.ndarray, P_next: np.ndarray) -> np.ndarray:
    """The Rauch-Tung-Striebel gains C = P+_k F' (P-_{k+1})^-1 of a stack of steps, from
    `FP` = F P+_k and the next step's prior covariance `P_next`, both (..., d, d).

    A solve of the symmetric P- against F P+; where some P- is singular, its
    pseudo-inverse (for all: one batched eigendecomposition, slower than the solve). A
    state the model never lets vary (a drift rate of zero prior sigma beside a drift walk,
    a correlation length so long that the grid sees none) leaves P- singular, and a
    direction of zero variance teaches the smoother nothing.
    """
    try:
        return np.linalg.solve(P_next, FP).swapaxes(-1, -2)
    except np.linalg.LinAlgError:
        return FP.swapaxes(-1, -2) @ np.linalg.pinv(P_next, hermitian=True)


def rts_smooth(
    x_prior: np.ndarray, P_prior: np.ndarray, x_post: np.ndarray, P_post: np.ndarray, F: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel fixed-interval smoothing of a filtered sequence of n steps.

    x_* are (n, d), P_* (n, d, d); F[k] (n, d, d) is the transition onto step k
    (F[0] is unused). Returns the smoothed states (n, d) and covariances
    (n, d, d): C_k = P+_k F'_{k+1} (P-_{k+1})^-1, xs_k = x+_k + C_k (xs_{k+1} -
    x-_{k+1}), Ps_k = P+_k + C_k (Ps_{k+1} - P-_{k+1}) C_k'. The last step's
    smoothed estimate is its filtered one.
    """
    xs, Ps = x_post.copy(), P_post.copy()
    # Every gain at once: they depend on the filter's covariances only.
    gains = rts_gains(F[1:] @ P_post[:-1], P_prior[1:])
    for k in range(x_post.shape[0] - 2, -1, -1):
        C = gains[k]
        xs[k] = x_post[k] + C @ (xs[k + 1] - x_prior[k + 1])
        Ps[k] = P_post[k] + C @ (Ps[k + 1] - P_prior[k + 1]) @ C.T
    return xs, Ps


class PathEstimator(ABC):
    """The height along the serpentine path, as `KalmanStrategy` drives it (heights in um).

    Calls per tile: `predict(step, dt_s)` (not on the first tile), then either
    `update(z_um, R_um2)` or `skip()`; `inflate` may come between them.
    """

    @property
    @abstractmethod
    def height(self) -> tuple[float, float]:
        """The current tile's height estimate: mean in um and variance in um^2."""

    @abstractmethod
    def predict(self, step: Step, dt_s: float = 0.0) -> None:
        """Move the estimate onto the next tile, reached by `step` `dt_s` seconds after the
        last tile (the time matters to a filter with a time state only)."""

    @abstractmethod
    def update(self, z_um: float, R_um2: float) -> None:
        """Correct the current tile's estimate with a measured height of variance `R_um2`."""

    @abstractmethod
    def skip(self) -> None:
        """Finish the current tile without a measurement (its posterior is its prior)."""

    @abstractmethod
    def inflate(self, var_um2: float) -> None:
        """Add `var_um2` to the current tile's height variance (the surface has moved)."""

    @abstractmethod
    def smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        """RTS-smoothed heights (n,) in um and variances (n,) in um^2 of the n finished tiles."""


class PathFilter(PathEstimator):
    """One `StateSpaceModel` under a Kalman filter: FilterPy's, or with `sqrt` our QR one.

    Both forms run the same model through the same predict(F, Q) / update(z, R)
    calls; the square-root form (`sqrt_filter.SqrtKalmanFilter`) keeps P
    symmetric and positive definite where round-off breaks the covariance form.
    With a `drift` (`time_state`), the state ends with the drift since the scan
    began and its rate: each step moves them on by its time, and a tile's focus is
    its height plus the drift (H = [1, 0, ..., 1, 0]).
    """

    def __init__(
        self,
        model: StateSpaceModel,
        settings: SlideSettings,
        *,
        sqrt: bool,
        drift: DriftModel | None = None,
    ) -> None:
        self.model = model
        self.drift = drift
        n = model.n_states + (N_DRIFT if drift is not None else 0)
        self._kf: KalmanFilter | SqrtKalmanFilter = (
            SqrtKalmanFilter(dim_x=n, dim_z=1) if sqrt else KalmanFilter(dim_x=n, dim_z=1)
        )
        x = np.zeros((n, 1))
        x[0, 0] = settings.start_z_um
        self._kf.x = x
        P = model.initial_covariance(settings.start_sigma_um)
        H = model.measurement_matrix
        if drift is not None:
            P = scipy.linalg.block_diag(P, drift.initial_covariance())
            H = np.hstack([H, [[1.0, 0.0]]])
        self._kf.P = P
        self._kf.H = H
        self._transition = self._timed(Step.START, 0.0)
        # Per tile in path order (RTS): prior and posterior state and covariance, F onto it.
        self._x_prior: list[np.ndarray] = [self._kf.x.copy()]
        self._P_prior: list[np.ndarray] = [self._kf.P.copy()]
        self._F: list[np.ndarray] = [self._transition.F]
        self._x_post: list[np.ndarray] = []
        self._P_post: list[np.ndarray] = []

    @property
    def x(self) -> np.ndarray:
        """The state (n_states, 1): height first, then the model's derivatives."""
        return self._kf.x

    @property
    def P(self) -> np.ndarray:  # noqa: N802 (the equations' name)
        """The state covariance (n_states, n_states)."""
        return self._kf.P

    @property
    def height(self) -> tuple[float, float]:
        if self.drift is None:
            return self._kf.x[0, 0].item(), self._kf.P[0, 0].item()
        H = self._kf.H
        return (H @ self._kf.x).item(), (H @ self._kf.P @ H.T).item()

    def _timed(self, step: Step, dt_s: float) -> Transition:
        """The model's transition for `step`, with the drift's over `dt_s` where there is one."""
        transition = self.model.transition(step)
        if self.drift is None:
            return transition
        F, Q = self.drift.transition(dt_s)
        return Transition(
            scipy.linalg.block_diag(transition.F, F),
            scipy.linalg.block_diag(transition.Q, Q),
            np.concatenate([transition.updated, np.ones(N_DRIFT, dtype=bool)]),
        )

    def predict(self, step: Step, dt_s: float = 0.0) -> None:
        self._transition = self._timed(step, dt_s)
        self._kf.predict(F=self._transition.F, Q=self._transition.Q)
        self._x_prior.append(self._kf.x.copy())
        self._P_prior.append(self._kf.P.copy())
        self._F.append(self._transition.F)

    def update(self, z_um: float, R_um2: float) -> None:
        updated = self._transition.updated
        if updated.all():
            self._kf.update(np.array([[z_um]]), R=R_um2)  # z as a column (ENGINEERING_NOTES)
        else:
            self._masked_update(z_um, R_um2, updated)
        self._finish()

    def _masked_update(self, z_um: float, R_um2: float, updated: np.ndarray) -> None:
        """An update that corrects only the states in `updated` (thesis Algorithm 2, line 15).

        The gain of the other states is zeroed; the Joseph form keeps P exact for
        that sub-optimal gain (as FilterPy's own update does). In the square-root
        form the new P is factored again, as it has no triangular update.
        """
        x, P, H = self._kf.x, self._kf.P, self._kf.H
        PHT = P @ H.T
        S_um2 = (H @ PHT).item() + R_um2
        K = np.where(updated[:, None], PHT / S_um2, 0.0)
        I_KH = np.eye(x.shape[0]) - K @ H
        self._kf.x = x + K * (z_um - (H @ x).item())
        self._kf.P = I_KH @ P @ I_KH.T + R_um2 * (K @ K.T)

    def skip(self) -> None:
        self._finish()

    def inflate(self, var_um2: float) -> None:
        # An extra identity step with noise at the height only: a triangular update in the
        # square-root form, P[0, 0] += var in the covariance form.
        n = self._kf.x.shape[0]
        Q = np.zeros((n, n))
        Q[0, 0] = var_um2
        self._kf.predict(F=np.eye(n), Q=Q)
        self._x_prior[-1], self._P_prior[-1] = self._kf.x.copy(), self._kf.P.copy()

    def _finish(self) -> None:
        self._x_post.append(self._kf.x.copy())
        self._P_post.append(self._kf.P.copy())

    def smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        n = len(self._x_post)
        if n == 0:
            return np.empty(0), np.empty(0)
        xs, Ps = rts_smooth(
            np.array(self._x_prior[:n])[..., 0],
            np.array(self._P_prior[:n]),
            np.array(self._x_post)[..., 0],
            np.array(self._P_post),
            np.array(self._F[:n]),
        )
        if self.drift is None:
            return xs[:, 0], Ps[:, 0, 0]
        h = self._kf.H[0]  # the focus: the height plus the drift
        return xs @ h, np.einsum("i,nij,j->n", h, Ps, h)


class KalmanStrategy(SerpentineFilter):
    """The serpentine loop around a `PathEstimator` (one Kalman filter, or a bank of them).

    On each tile the estimator predicts once with the model's F and Q for the
    step that led there (thesis Algorithm 2, lines 7-14); a measurement updates
    it, a tile without one is skipped (its posterior is its prior). The focus
    map carries the RTS-smoothed layers over the tiles finished so far.
    """

    def __init__(
        self,
        settings: SlideSettings,
        estimator: PathEstimator,
        *,
        name: str,
        options: FilterParams,
    ) -> None:
        super().__init__(settings, options)
        self.name = name
        self.estimator = estimator
        self._smoothed_at = -1  # tiles finished when the smoothed layers were last filled
        self._state_s = 0.0  # the scan's time of the estimator's state

    def focus_map(self) -> FocusMap:
        """The estimates so far, with the RTS-smoothed layers over the tiles finished so far."""
        if self._position and self._smoothed_at != self._position:
            smoothed_um, smoothed_var_um2 = self.estimator.smoothed()
            self.map.smoothed_um = np.full(self.grid.shape, np.nan)
            self.map.smoothed_sigma_um = np.full(self.grid.shape, np.nan)
            for tile, mean_um, var_um2 in zip(
                self.grid.serpentine, smoothed_um, smoothed_var_um2, strict=False
            ):
                self.map.smoothed_um[tile.row, tile.col] = mean_um
                self.map.smoothed_sigma_um[tile.row, tile.col] = math.sqrt(max(var_um2, 0.0))
            self._smoothed_at = self._position
        return self.map

    def _predict(self, tile: Tile) -> Gaussian:
        if self._position > 0:
            arrival_s = self.clock.arrival_s(self.grid, tile)
            self.estimator.predict(self.grid.steps[self._position], arrival_s - self._state_s)
            self._state_s = arrival_s
        return Gaussian(*self.estimator.height)

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        if z_um is None:
            self.estimator.skip()
            return prior
        self.estimator.update(z_um, R_um2)
        return Gaussian(*self.estimator.height)

    def _inflate(self, var_um2: float) -> None:
        self.estimator.inflate(var_um2)


# Parameters and factories: defaults are tuned on training maps by `focustrack.bench.tune`
# (docs/estimators.md). Each model extends `FilterParams` (retries, the lean rule, the NIS
# gate, the adaptive R and the square-root form, off by default: these are the thesis'
# filters).

QHeightUm2 = Annotated[
    float,
    Field(
        ge=0.0,
        description="Variance of white noise entering at the height itself on each step, "
        "um^2 (absorbs an isolated jump of the surface instead of bending the gradient)",
    ),
]
SlopeSigmaUmPerTile = Annotated[
    float, Field(ge=0.0, description="Prior std of the gradient (the filter starts at 0), um/tile")
]


class KfWiener0Params(FilterParams, TimeStateParams):
    """kf-wiener0: Zhang et al.'s random walk (thesis eq. 3-23, order 0)."""

    q: float = Field(
        0.14,
        ge=0.0,
        description="Spectral density of the white noise driving the height, um^2/tile",
    )


class KfWiener1Params(FilterParams, TimeStateParams):
    """kf-wiener1: height and gradient along the path; the gradient is a Wiener process."""

    q: float = Field(
        1e-8,
        ge=0.0,
        description="Spectral density of the white noise driving the gradient, um^2/tile^3",
    )
    q_height_um2: QHeightUm2 = 0.2
    slope_sigma_um_per_tile: SlopeSigmaUmPerTile = 0.5


class KfWiener2Params(FilterParams, TimeStateParams):
    """kf-wiener2: height, gradient and curvature along the path; the curvature is a Wiener
    process."""

    q: float = Field(
        1e-10,
        ge=0.0,
        description="Spectral density of the white noise driving the curvature, um^2/tile^5",
    )
    q_height_um2: QHeightUm2 = 0.2
    slope_sigma_um_per_tile: SlopeSigmaUmPerTile = 0.5
    curvature_sigma_um_per_tile2: float = Field(
        0.1, ge=0.0, description="Prior std of the curvature (the filter starts at 0), um/tile^2"
    )


def _positive_semidefinite(order: int) -> AfterValidator:
    """A check that the Gauss-Markov model of `order` has a valid Q at a beta (a ValueError
    naming the least beta where not: `models.gauss_markov_process_noise`)."""

    def check(beta_per_tile: float) -> float:
        gauss_markov_process_noise(order, 1.0, beta_per_tile)  # sigma only scales Q
        return beta_per_tile

    return AfterValidator(check)


BetaPerTile = Field(
    gt=0.0,
    description="Inverse correlation length of the Gauss-Markov derivative, 1/tile (the "
    "thesis' closed-form Q needs beta >= 5.98 for order 1, >= 20.99 for order 2)",
)


class KfGm1Params(FilterParams, TimeStateParams):
    """kf-gm1: height and a Gauss-Markov gradient (thesis eq. 3-33..3-47, order 1)."""

    sigma: float = Field(
        0.7, gt=0.0, description="Stationary std of the Gauss-Markov gradient, um/tile"
    )
    beta_per_tile: Annotated[float, BetaPerTile, _positive_semidefinite(1)] = 8.0
    q_height_um2: QHeightUm2 = 0.01


class KfGm2Params(FilterParams, TimeStateParams):
    """kf-gm2: height, gradient and a Gauss-Markov curvature (order 2)."""

    sigma: float = Field(
        0.01, gt=0.0, description="Stationary std of the Gauss-Markov curvature, um/tile^2"
    )
    beta_per_tile: Annotated[float, BetaPerTile, _positive_semidefinite(2)] = 100.0
    q_height_um2: QHeightUm2 = 0.2
    slope_sigma_um_per_tile: SlopeSigmaUmPerTile = 0.5


class KfWiener1DirParams(FilterParams, TimeStateParams):
    """kf-wiener1-dir: the direction-aware first-order filter (thesis eq. 3-54, 3-55,
    Algorithm 2): x and y gradients in slide coordinates."""

    q: float = Field(
        1e-4,
        ge=0.0,
        description="Spectral density of the white noise driving each gradient, um^2/tile^3",
    )
    q_height_um2: QHeightUm2 = 0.0
    slope_sigma_um_per_tile: SlopeSigmaUmPerTile = 0.5
    partitioned: bool = Field(
        False,
        description="Correct only the height and the gradient along the last step (thesis "
        "Algorithm 2, line 15) instead of every state",
    )


def kalman_strategy(
    settings: SlideSettings, model: StateSpaceModel, name: str, params: FilterParams
) -> KalmanStrategy:
    """A `KalmanStrategy` over one model's `PathFilter` (the factories' common tail)."""
    estimator = PathFilter(model, settings, sqrt=params.sqrt, drift=DriftModel.of(params))
    return KalmanStrategy(settings, estimator, name=name, options=params)


def kf_wiener0(settings: SlideSettings, params: KfWiener0Params) -> KalmanStrategy:
    """Zhang et al.'s random walk: the height is a Wiener process (thesis eq. 3-23, order 0)."""
    return kalman_strategy(settings, WienerModel(0, params.q), "kf-wiener0", params)


def kf_wiener1(settings: SlideSettings, params: KfWiener1Params) -> KalmanStrategy:
    """Height and gradient along the path; the gradient is a Wiener process (order 1)."""
    model = WienerModel(
        1,
        params.q,
        q_height_um2=params.q_height_um2,
        slope_sigma_um_per_tile=params.slope_sigma_um_per_tile,
    )
    return kalman_strategy(settings, model, "kf-wiener1", params)


def kf_wiener2(settings: SlideSettings, params: KfWiener2Params) -> KalmanStrategy:
    """Height, gradient and curvature along the path; the curvature is a Wiener process."""
    model = WienerModel(
        2,
        params.q,
        q_height_um2=params.q_height_um2,
        slope_sigma_um_per_tile=params.slope_sigma_um_per_tile,
        curvature_sigma_um_per_tile2=params.curvature_sigma_um_per_tile2,
    )
    return kalman_strategy(settings, model, "kf-wiener2", params)


def kf_gm1(settings: SlideSettings, params: KfGm1Params) -> KalmanStrategy:
    """Height and a Gauss-Markov gradient (std `sigma` um/tile, eq. 3-33..3-47, order 1)."""
    model = GaussMarkovModel(
        1, params.sigma, params.beta_per_tile, q_height_um2=params.q_height_um2
    )
    return kalman_strategy(settings, model, "kf-gm1", params)


def kf_gm2(settings: SlideSettings, params: KfGm2Params) -> KalmanStrategy:
    """Height, gradient and a Gauss-Markov curvature (std `sigma` um/tile^2, order 2)."""
    model = GaussMarkovModel(
        2,
        params.sigma,
        params.beta_per_tile,
        q_height_um2=params.q_height_um2,
        slope_sigma_um_per_tile=params.slope_sigma_um_per_tile,
    )
    return kalman_strategy(settings, model, "kf-gm2", params)


def kf_wiener1_dir(settings: SlideSettings, params: KfWiener1DirParams) -> KalmanStrategy:
    """The direction-aware first-order filter (thesis eq. 3-54, 3-55, Algorithm 2)."""
    model = DirectionAwareModel(
        params.q,
        q_height_um2=params.q_height_um2,
        slope_sigma_um_per_tile=params.slope_sigma_um_per_tile,
        partitioned=params.partitioned,
    )
    return kalman_strategy(settings, model, "kf-wiener1-dir", params)


#: Bytes a `PathFilter` keeps per tile for its smoother (prior and posterior state and
#: covariance, as small numpy arrays of about 200 bytes each) and the smoother's arrays.
PATH_BYTES_PER_TILE = 2_000


def path_cost(n_members: int) -> CostModel[StrategyParams]:
    """The cost model of a strategy over `n_members` `PathFilter`s of at most three states:
    memory linear in the tiles (the smoother's history), constant work per tile."""

    def cost(settings: SlideSettings, params: StrategyParams) -> Cost:
        n_tiles = settings.grid.n_tiles
        return tile_cost(settings) + Cost(n_members * n_tiles * PATH_BYTES_PER_TILE, 0.0)

    return cost


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "kf-wiener0": StrategyEntry(KfWiener0Params, kf_wiener0, path_cost(1)),
    "kf-wiener1": StrategyEntry(KfWiener1Params, kf_wiener1, path_cost(1)),
    "kf-wiener2": StrategyEntry(KfWiener2Params, kf_wiener2, path_cost(1)),
    "kf-gm1": StrategyEntry(KfGm1Params, kf_gm1, path_cost(1)),
    "kf-gm2": StrategyEntry(KfGm2Params, kf_gm2, path_cost(1)),
    "kf-wiener1-dir": StrategyEntry(KfWiener1DirParams, kf_wiener1_dir, path_cost(1)),
}
