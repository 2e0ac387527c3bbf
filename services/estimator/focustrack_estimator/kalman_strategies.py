"""Kalman-filter scan strategies: predict the next tile's focus, stack narrowly around it, learn.

Two layers:

- `PathEstimator`: the height along the serpentine path, as a Kalman filter
  sees it: `predict(step)`, `update(z, R)`, `skip()` (a tile left without a
  measurement), `inflate(var)` and `smoothed()`. `PathFilter` is one
  `StateSpaceModel` under a FilterPy `KalmanFilter` (or, with `sqrt=True`, the
  QR square-root filter of `sqrt_filter`); `bank.ModelBank` blends several.
  Each keeps, per finished tile, the prior and posterior state and the F of the
  step onto the tile: what the Rauch-Tung-Striebel smoother needs.
- `KalmanStrategy`: the scan shell around any estimator. On each tile the
  estimator predicts once with the model's F and Q for the step that led there;
  the stack is taken over the prediction +/- k innovation sigmas
  (`ZRangePolicy.around`, sigma = sqrt(H P H^T + R)); the best focus found in
  it updates the estimator. A peak at the edge of the stack (or a flat curve)
  is no measurement: the same tile is acquired again beyond that edge
  (`PeakSearch`), with no second predict; when the search ends without a
  peak the tile is given up (imaged at its prediction, marked in
  `gave_up`) so that a scan always ends. A tile is imaged
  (`FocusMap.z_used_um`) at the frame nearest its posterior among all the
  stacks taken on it.

Noise that adapts (docs/estimators.md): a measurement's own `sigma_um` is its
R; with `gate_nis` > 0 a measurement whose NIS exceeds it is rejected (an
outlier: dust, a parasite in another plane) unless `gate_patience` measurements
in a row were rejected before it, in which case the surface really moved (a
fold, a step): it is accepted after the height's variance is inflated by the
squared innovation. With `adapt_r` the default R (for measurements without a
sigma) is estimated online by covariance matching of the innovations.

Strategies are deterministic functions of the measurements they are given, so
replaying a slide's measurement log rebuilds the same filter.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from filterpy.kalman import KalmanFilter

from focustrack_core.domain import Acquisition, FocusMap, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import Step
from focustrack_estimator.models import (
    DirectionAwareModel,
    GaussMarkovModel,
    StateSpaceModel,
    WienerModel,
)
from focustrack_estimator.sqrt_filter import SqrtKalmanFilter
from focustrack_estimator.strategy import PeakSearch, SlideSettings, Strategy

#: How many measurements the configured default R counts as when `adapt_r` estimates it.
R_PRIOR_COUNT = 20


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
    for k in range(x_post.shape[0] - 2, -1, -1):
        # C = P+ F' (P-)^-1, as the solve of the symmetric P- against F P+.
        C = np.linalg.solve(P_prior[k + 1], F[k + 1] @ P_post[k]).T
        xs[k] = x_post[k] + C @ (xs[k + 1] - x_prior[k + 1])
        Ps[k] = P_post[k] + C @ (Ps[k + 1] - P_prior[k + 1]) @ C.T
    return xs, Ps


class PathEstimator(ABC):
    """The height along the serpentine path, as `KalmanStrategy` drives it (heights in um).

    Calls per tile: `predict(step)` (not on the first tile), then either
    `update(z_um, R_um2)` or `skip()`; `inflate` may come between them.
    """

    @property
    @abstractmethod
    def height(self) -> tuple[float, float]:
        """The current tile's height estimate: mean in um and variance in um^2."""

    @abstractmethod
    def predict(self, step: Step) -> None:
        """Move the estimate onto the next tile, reached by `step`."""

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
    """

    def __init__(self, model: StateSpaceModel, settings: SlideSettings, *, sqrt: bool) -> None:
        self.model = model
        n = model.n_states
        self._kf: KalmanFilter | SqrtKalmanFilter = (
            SqrtKalmanFilter(dim_x=n, dim_z=1) if sqrt else KalmanFilter(dim_x=n, dim_z=1)
        )
        x = np.zeros((n, 1))
        x[0, 0] = settings.start_z_um
        self._kf.x = x
        self._kf.P = model.initial_covariance(settings.start_sigma_um)
        self._kf.H = model.measurement_matrix
        self._transition = model.transition(Step.START)
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
        return self._kf.x[0, 0].item(), self._kf.P[0, 0].item()

    def predict(self, step: Step) -> None:
        self._transition = self.model.transition(step)
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
        x, P, H = self._kf.x, self._kf.P, self.model.measurement_matrix
        PHT = P @ H.T
        S_um2 = (H @ PHT).item() + R_um2
        K = np.where(updated[:, None], PHT / S_um2, 0.0)
        I_KH = np.eye(x.shape[0]) - K @ H
        self._kf.x = x + K * (z_um - x[0, 0])
        self._kf.P = I_KH @ P @ I_KH.T + R_um2 * (K @ K.T)

    def skip(self) -> None:
        self._finish()

    def inflate(self, var_um2: float) -> None:
        # An extra identity step with noise at the height only: a triangular update in the
        # square-root form, P[0, 0] += var in the covariance form.
        n = self.model.n_states
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
        return xs[:, 0], Ps[:, 0, 0]


class KalmanStrategy(Strategy):
    """A scan strategy driven by a `PathEstimator` (one Kalman filter, or a bank of them).

    `gave_up` (rows, cols) marks tiles imaged at their prediction because no
    stack found a peak within `max_retries` retries; `gated` marks tiles whose
    measurement was rejected by the NIS gate (imaged at their prediction too).
    gate_nis: NIS threshold of the gate (0: no gating; chi-square with one degree
    of freedom for a consistent filter, `diagnostics.nis_gate`); gate_patience:
    rejections in a row after which an outlier is taken as a real step;
    adapt_r: estimate the default R online from the innovations.
    """

    def __init__(
        self,
        settings: SlideSettings,
        estimator: PathEstimator,
        *,
        name: str,
        max_retries: int,
        gate_nis: float = 0.0,
        gate_patience: int = 1,
        adapt_r: bool = False,
    ) -> None:
        super().__init__(settings)
        if gate_nis < 0 or gate_patience < 0:
            raise ValueError(
                f"gate_nis and gate_patience must not be negative, got {gate_nis}, {gate_patience}"
            )
        self.name = name
        self.estimator = estimator
        self.max_retries = max_retries
        self.gate_nis = gate_nis
        self.gate_patience = gate_patience
        self.adapt_r = adapt_r
        self.gave_up = np.zeros(self.grid.shape, dtype=bool)
        self.gated = np.zeros(self.grid.shape, dtype=bool)
        self._rejected_in_a_row = 0
        # Default R as a running mean of R_PRIOR_COUNT copies of the configured value and
        # one estimate per innovation (covariance matching: E[y^2] = H P H' + R).
        self._r_sum_um2 = R_PRIOR_COUNT * settings.noise_sigma_um**2
        self._r_count = R_PRIOR_COUNT
        self._r_min_um2 = 1e-2 * settings.noise_sigma_um**2
        self._position = 0  # index of the current tile in serpentine order
        self._search = PeakSearch(settings.policy, max_retries)  # on the current tile
        self._innovation_um: list[float] = []
        self._innovation_var_um2: list[float] = []
        self._smoothed_at = -1  # tiles finished when the smoothed layers were last filled
        self._enter_tile()

    @property
    def default_r_um2(self) -> float:
        """The variance of a measurement that comes without a sigma (estimated if `adapt_r`)."""
        # Single terms y^2 - H P H' may be negative; only the mean must stay positive.
        return max(self._r_sum_um2 / self._r_count, self._r_min_um2)

    def innovations(self) -> tuple[np.ndarray, np.ndarray]:
        """Accepted innovations (n,) in um and their predicted variances S (n,) in um^2.

        In scan order, for `diagnostics.innovation_diagnostics` (gated-out
        measurements are not innovations of the filter: their NIS is in their Outcome).
        """
        return np.array(self._innovation_um), np.array(self._innovation_var_um2)

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

    @property
    def _prior(self) -> tuple[float, float]:
        """The current tile's predicted height and its std, in um."""
        row, col = self._tile
        return float(self.map.prior_um[row, col]), float(self.map.prior_sigma_um[row, col])

    @property
    def _tile(self) -> tuple[int, int]:
        tile = self.grid.serpentine[self._position]
        return tile.row, tile.col

    def _enter_tile(self) -> None:
        """Predict the current tile from the last (thesis Algorithm 2, lines 7-14)."""
        if self._position > 0:
            self.estimator.predict(self.grid.steps[self._position])
        row, col = self._tile
        mean_um, var_um2 = self.estimator.height
        self.map.prior_um[row, col] = mean_um
        self.map.prior_sigma_um[row, col] = math.sqrt(var_um2)
        self._search.clear()

    def _plan(self) -> Acquisition | None:
        if self._position >= self.grid.n_tiles:
            return None
        row, col = self._tile
        prior_um, prior_sigma_um = self._prior
        policy = self.settings.policy
        if not self._search:
            innovation_sigma_um = math.sqrt(prior_sigma_um**2 + self.default_r_um2)
            z, purpose = policy.around(prior_um, innovation_sigma_um), Purpose.SCAN
        else:
            z, purpose = self._search.next_range(), Purpose.RETRY
        return self._acquisition(
            row,
            col,
            z,
            purpose,
            measure=True,
            predicted_um=prior_um,
            predicted_sigma_um=prior_sigma_um,
        )

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        row, col = self._tile
        prior_um, prior_sigma_um = self._prior
        if measurement.z_um is None or not measurement.is_observation:
            return self._no_peak(acquisition.z, measurement, prior_um, prior_sigma_um)

        R_um2 = self.default_r_um2 if measurement.sigma_um is None else measurement.sigma_um**2
        innovation_um = measurement.z_um - prior_um
        variance_um2 = prior_sigma_um**2 + R_um2
        nis = innovation_um**2 / variance_um2
        outcome = Outcome(
            row,
            col,
            accepted=True,
            prior_um=prior_um,
            prior_sigma_um=prior_sigma_um,
            innovation_um=innovation_um,
            nis=nis,
        )
        if self.gate_nis and nis > self.gate_nis:
            if self._rejected_in_a_row < self.gate_patience:
                # An outlier: the tile keeps its prediction and is imaged there.
                self._rejected_in_a_row += 1
                self.gated[row, col] = True
                self.estimator.skip()
                self._finish_tile(prior_um, prior_sigma_um, acquisition.z)
                return replace(
                    outcome,
                    accepted=False,
                    posterior_um=prior_um,
                    posterior_sigma_um=prior_sigma_um,
                )
            # Outliers in a row are the surface itself moving (a fold, a step): take it.
            self.estimator.inflate(innovation_um**2)
            variance_um2 += innovation_um**2
        self._rejected_in_a_row = 0
        self.estimator.update(measurement.z_um, R_um2)
        if self.adapt_r and measurement.sigma_um is None:
            self._r_sum_um2 += innovation_um**2 - (variance_um2 - R_um2)
            self._r_count += 1
        self._innovation_um.append(innovation_um)
        self._innovation_var_um2.append(variance_um2)
        posterior_um, posterior_var_um2 = self.estimator.height
        posterior_sigma_um = math.sqrt(posterior_var_um2)
        self._finish_tile(posterior_um, posterior_sigma_um, acquisition.z)
        return replace(
            outcome,
            posterior_um=posterior_um,
            posterior_sigma_um=posterior_sigma_um,
            nis=innovation_um**2 / variance_um2,
        )

    def _no_peak(
        self, stack: ZRange, measurement: Measurement, prior_um: float, prior_sigma_um: float
    ) -> Outcome:
        """No peak in the stack: take another (`PeakSearch`), or give the tile up."""
        row, col = self._tile
        if not self._search.failed(stack, measurement):
            # The first stack was centred on the prediction: image the tile there.
            self.gave_up[row, col] = True
            self.estimator.skip()
            self._finish_tile(prior_um, prior_sigma_um)
            return Outcome(
                row,
                col,
                accepted=False,
                prior_um=prior_um,
                prior_sigma_um=prior_sigma_um,
                posterior_um=prior_um,
                posterior_sigma_um=prior_sigma_um,
            )
        return Outcome(row, col, accepted=False, prior_um=prior_um, prior_sigma_um=prior_sigma_um)

    def _finish_tile(
        self, posterior_um: float, sigma_um: float, last_stack: ZRange | None = None
    ) -> None:
        """Record the tile's estimate, image it at the acquired frame nearest it, move on."""
        row, col = self._tile
        stacks = self._search.stacks + ([last_stack] if last_stack else [])
        frames_um = np.concatenate([stack.z_um() for stack in stacks])
        self.map.posterior_um[row, col] = posterior_um
        self.map.posterior_sigma_um[row, col] = sigma_um
        self.map.z_used_um[row, col] = frames_um[np.argmin(np.abs(frames_um - posterior_um))]
        self._position += 1
        if self._position < self.grid.n_tiles:
            self._enter_tile()


# Factories: `factory(settings, **params)`; keyword defaults are tuned on training maps by
# `focustrack.bench.tune` (docs/estimators.md). Units: q of the Wiener models is the
# spectral density of the noise on the highest derivative (um^2/tile for order 0,
# um^2/tile^3 for order 1, um^2/tile^5 for order 2). Every one also takes `sqrt` (run the
# model through the square-root filter) and the adaptive-noise options of `KalmanStrategy`
# (`gate_nis`, `gate_patience`, `adapt_r`), off by default: these are the thesis' filters.


def kalman_strategy(
    settings: SlideSettings,
    model: StateSpaceModel,
    name: str,
    *,
    max_retries: int,
    sqrt: bool,
    gate_nis: float,
    gate_patience: int,
    adapt_r: bool,
) -> KalmanStrategy:
    """A `KalmanStrategy` over one model's `PathFilter` (the factories' common tail)."""
    return KalmanStrategy(
        settings,
        PathFilter(model, settings, sqrt=sqrt),
        name=name,
        max_retries=max_retries,
        gate_nis=gate_nis,
        gate_patience=gate_patience,
        adapt_r=adapt_r,
    )


def kf_wiener0(
    settings: SlideSettings,
    *,
    q: float = 0.14,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """Zhang et al.'s random walk: the height is a Wiener process (thesis eq. 3-23, order 0)."""
    return kalman_strategy(
        settings, WienerModel(0, q), "kf-wiener0", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


def kf_wiener1(
    settings: SlideSettings,
    *,
    q: float = 1e-8,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """Height and gradient along the path; the gradient is a Wiener process (order 1)."""
    model = WienerModel(
        1, q, q_height_um2=q_height_um2, slope_sigma_um_per_tile=slope_sigma_um_per_tile
    )
    return kalman_strategy(
        settings, model, "kf-wiener1", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


def kf_wiener2(
    settings: SlideSettings,
    *,
    q: float = 1e-10,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    curvature_sigma_um_per_tile2: float = 0.1,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """Height, gradient and curvature along the path; the curvature is a Wiener process."""
    model = WienerModel(
        2,
        q,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
        curvature_sigma_um_per_tile2=curvature_sigma_um_per_tile2,
    )
    return kalman_strategy(
        settings, model, "kf-wiener2", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


def kf_gm1(
    settings: SlideSettings,
    *,
    sigma: float = 0.7,
    beta_per_tile: float = 8.0,
    q_height_um2: float = 0.01,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """Height and a Gauss-Markov gradient (std `sigma` um/tile, eq. 3-33..3-47, order 1)."""
    model = GaussMarkovModel(1, sigma, beta_per_tile, q_height_um2=q_height_um2)
    return kalman_strategy(
        settings, model, "kf-gm1", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


def kf_gm2(
    settings: SlideSettings,
    *,
    sigma: float = 0.01,
    beta_per_tile: float = 100.0,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """Height, gradient and a Gauss-Markov curvature (std `sigma` um/tile^2, order 2)."""
    model = GaussMarkovModel(
        2,
        sigma,
        beta_per_tile,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
    )
    return kalman_strategy(
        settings, model, "kf-gm2", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


def kf_wiener1_dir(
    settings: SlideSettings,
    *,
    q: float = 1e-4,
    q_height_um2: float = 0.0,
    slope_sigma_um_per_tile: float = 0.5,
    partitioned: bool = False,
    max_retries: int = 3,
    sqrt: bool = False,
    gate_nis: float = 0.0,
    gate_patience: int = 1,
    adapt_r: bool = False,
) -> KalmanStrategy:
    """The direction-aware first-order filter (thesis eq. 3-54, 3-55, Algorithm 2)."""
    model = DirectionAwareModel(
        q,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
        partitioned=partitioned,
    )
    return kalman_strategy(
        settings, model, "kf-wiener1-dir", max_retries=max_retries, sqrt=sqrt,
        gate_nis=gate_nis, gate_patience=gate_patience, adapt_r=adapt_r,
    )  # fmt: skip


STRATEGIES: dict[str, Callable[..., Strategy]] = {
    "kf-wiener0": kf_wiener0,
    "kf-wiener1": kf_wiener1,
    "kf-wiener2": kf_wiener2,
    "kf-gm1": kf_gm1,
    "kf-gm2": kf_gm2,
    "kf-wiener1-dir": kf_wiener1_dir,
}
