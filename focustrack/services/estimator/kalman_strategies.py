"""Kalman-filter scan strategies: predict the next tile's focus, stack narrowly around it, learn.

The grid is walked in serpentine order. On each tile the filter predicts once
with the model's F and Q for the step that led there (FilterPy's
`KalmanFilter.predict`); the stack is taken over the prediction +/- k innovation
sigmas (`ZRangePolicy.around`, sigma = sqrt(H P H^T + R)); the best focus found
in it updates the filter. A peak at the edge of the stack (or a flat curve) is
no measurement: the same tile is acquired again beyond that edge
(`ZRangePolicy.beyond`), with no second predict, and after `max_retries`
retries the tile is given up (imaged at its prediction, marked in `gave_up`) so
that a scan always ends. A tile is imaged (`FocusMap.z_used_um`) at the frame
nearest its posterior among all the stacks taken on it: after a retry the
posterior often lies back in the first stack, between prediction and peak.

Strategies are deterministic functions of the measurements they are given, so
replaying a slide's measurement log rebuilds the same filter.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from filterpy.kalman import KalmanFilter

from focustrack.services.estimator.models import (
    DirectionAwareModel,
    GaussMarkovModel,
    StateSpaceModel,
    WienerModel,
)
from focustrack.services.estimator.strategy import (
    Acquisition,
    FocusFlag,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    Strategy,
    ZRange,
)

_EDGES = frozenset({FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH})


def _masked_update(kf: KalmanFilter, z_um: float, R_um2: float, updated: np.ndarray) -> None:
    """A Kalman update that corrects only the states in `updated` (thesis Algorithm 2, line 15).

    The gain of the other states is zeroed; the Joseph form keeps P exact for
    that sub-optimal gain (as FilterPy's own update does).
    """
    H = kf.H
    kf.y = np.array([[z_um]]) - H @ kf.x
    PHT = kf.P @ H.T
    kf.S = H @ PHT + R_um2
    kf.K = np.where(updated[:, None], PHT / kf.S.item(), 0.0)
    kf.x = kf.x + kf.K @ kf.y
    I_KH = np.eye(kf.dim_x) - kf.K @ H
    kf.P = I_KH @ kf.P @ I_KH.T + R_um2 * (kf.K @ kf.K.T)
    kf.x_post, kf.P_post = kf.x.copy(), kf.P.copy()


class KalmanStrategy(Strategy):
    """A scan strategy driven by a linear Kalman filter over a `StateSpaceModel`.

    `gave_up` (rows, cols) marks tiles imaged at their prediction because no
    stack found a peak within `max_retries` retries.
    """

    def __init__(
        self, settings: SlideSettings, model: StateSpaceModel, *, name: str, max_retries: int
    ) -> None:
        super().__init__(settings)
        if max_retries < 0:
            raise ValueError(f"max_retries must not be negative, got {max_retries}")
        self.name = name
        self.model = model
        self.max_retries = max_retries
        self.gave_up = np.zeros(self.grid.shape, dtype=bool)
        self._kf = KalmanFilter(dim_x=model.n_states, dim_z=1)
        self._kf.x = np.zeros((model.n_states, 1))
        self._kf.x[0, 0] = settings.start_z_um
        self._kf.P = model.initial_covariance(settings.start_sigma_um)
        self._kf.H = model.measurement_matrix
        self._kf.R = np.array([[settings.noise_sigma_um**2]])
        self._position = 0  # index of the current tile in serpentine order
        self._misses: list[tuple[ZRange, FocusFlag]] = []  # peakless stacks on the current tile
        self._innovation_um: list[float] = []
        self._innovation_var_um2: list[float] = []
        self._enter_tile()

    def innovations(self) -> tuple[np.ndarray, np.ndarray]:
        """Innovations (n,) in um and their predicted variances S (n,) in um^2, in scan order.

        For `focustrack.services.estimator.diagnostics.innovation_diagnostics`.
        """
        return np.array(self._innovation_um), np.array(self._innovation_var_um2)

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
        transition = self.model.transition(self.grid.steps[self._position])
        if self._position > 0:
            self._kf.predict(F=transition.F, Q=transition.Q)
        row, col = self._tile
        self.map.prior_um[row, col] = self._kf.x[0, 0]
        self.map.prior_sigma_um[row, col] = math.sqrt(
            (self._kf.H @ self._kf.P @ self._kf.H.T).item()
        )
        self._misses = []

    def _plan(self) -> Acquisition | None:
        if self._position >= self.grid.n_tiles:
            return None
        row, col = self._tile
        prior_um, prior_sigma_um = self._prior
        policy = self.settings.policy
        if not self._misses:
            innovation_sigma_um = math.hypot(prior_sigma_um, self.settings.noise_sigma_um)
            z, purpose = policy.around(prior_um, innovation_sigma_um), Purpose.SCAN
        else:
            z, purpose = self._retry_range(), Purpose.RETRY
        return self._acquisition(
            row,
            col,
            z,
            purpose,
            measure=True,
            predicted_um=prior_um,
            predicted_sigma_um=prior_sigma_um,
        )

    def _retry_range(self) -> ZRange:
        """The stack after peakless ones: between two that bracket the peak, else beyond the last.

        A peak near the boundary of two stacks can leave each with only one
        flank (one says EDGE_HIGH, the other EDGE_LOW); the peak then lies
        between the highest EDGE_HIGH edge and the lowest EDGE_LOW edge, which
        may overlap by the frames the stacks share.
        """
        policy = self.settings.policy
        above_um = max(
            (z.high_um for z, flag in self._misses if flag is FocusFlag.EDGE_HIGH),
            default=-math.inf,
        )
        below_um = min(
            (z.low_um for z, flag in self._misses if flag is FocusFlag.EDGE_LOW), default=math.inf
        )
        if math.isfinite(above_um) and math.isfinite(below_um):
            half_width_um = abs(below_um - above_um) / 2.0 + policy.z_step_um
            return policy.around((above_um + below_um) / 2.0, half_width_um / policy.k_sigma)
        return policy.beyond(*self._misses[-1])

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        row, col = self._tile
        prior_um, prior_sigma_um = self._prior
        if not measurement.is_observation:
            return self._no_peak(acquisition.z, measurement, prior_um, prior_sigma_um)

        sigma_um = measurement.sigma_um or self.settings.noise_sigma_um
        updated = self.model.transition(self.grid.steps[self._position]).updated
        if updated.all():
            self._kf.update(np.array([[measurement.z_um]]), R=sigma_um**2)
        else:
            _masked_update(self._kf, measurement.z_um, sigma_um**2, updated)
        innovation_um, variance_um2 = self._kf.y.item(), self._kf.S.item()
        self._innovation_um.append(innovation_um)
        self._innovation_var_um2.append(variance_um2)
        posterior_um = self._kf.x[0, 0].item()
        posterior_sigma_um = math.sqrt(self._kf.P[0, 0])
        self._finish_tile(posterior_um, posterior_sigma_um, acquisition.z)
        return Outcome(
            row,
            col,
            accepted=True,
            prior_um=prior_um,
            prior_sigma_um=prior_sigma_um,
            posterior_um=posterior_um,
            posterior_sigma_um=posterior_sigma_um,
            innovation_um=innovation_um,
            nis=innovation_um**2 / variance_um2,
        )

    def _no_peak(
        self, stack: ZRange, measurement: Measurement, prior_um: float, prior_sigma_um: float
    ) -> Outcome:
        """An edge peak or a flat curve: retry (see `_retry_range`), or give the tile up."""
        row, col = self._tile
        edges = measurement.flags & _EDGES
        self._misses.append((stack, next(iter(edges)) if len(edges) == 1 else FocusFlag.FLAT))
        if len(self._misses) > self.max_retries:
            # The first stack was centred on the prediction: image the tile there.
            self.gave_up[row, col] = True
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
        stacks = [stack for stack, _ in self._misses] + ([last_stack] if last_stack else [])
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
# um^2/tile^3 for order 1, um^2/tile^5 for order 2).


def kf_wiener0(settings: SlideSettings, *, q: float = 0.14, max_retries: int = 3) -> KalmanStrategy:
    """Zhang et al.'s random walk: the height is a Wiener process (thesis eq. 3-23, order 0)."""
    return KalmanStrategy(settings, WienerModel(0, q), name="kf-wiener0", max_retries=max_retries)


def kf_wiener1(
    settings: SlideSettings,
    *,
    q: float = 1e-8,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    max_retries: int = 3,
) -> KalmanStrategy:
    """Height and gradient along the path; the gradient is a Wiener process (order 1)."""
    model = WienerModel(
        1, q, q_height_um2=q_height_um2, slope_sigma_um_per_tile=slope_sigma_um_per_tile
    )
    return KalmanStrategy(settings, model, name="kf-wiener1", max_retries=max_retries)


def kf_wiener2(
    settings: SlideSettings,
    *,
    q: float = 1e-10,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    curvature_sigma_um_per_tile2: float = 0.1,
    max_retries: int = 3,
) -> KalmanStrategy:
    """Height, gradient and curvature along the path; the curvature is a Wiener process."""
    model = WienerModel(
        2,
        q,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
        curvature_sigma_um_per_tile2=curvature_sigma_um_per_tile2,
    )
    return KalmanStrategy(settings, model, name="kf-wiener2", max_retries=max_retries)


def kf_gm1(
    settings: SlideSettings,
    *,
    sigma: float = 0.7,
    beta_per_tile: float = 8.0,
    q_height_um2: float = 0.01,
    max_retries: int = 3,
) -> KalmanStrategy:
    """Height and a Gauss-Markov gradient (std `sigma` um/tile, eq. 3-33..3-47, order 1)."""
    model = GaussMarkovModel(1, sigma, beta_per_tile, q_height_um2=q_height_um2)
    return KalmanStrategy(settings, model, name="kf-gm1", max_retries=max_retries)


def kf_gm2(
    settings: SlideSettings,
    *,
    sigma: float = 0.01,
    beta_per_tile: float = 100.0,
    q_height_um2: float = 0.2,
    slope_sigma_um_per_tile: float = 0.5,
    max_retries: int = 3,
) -> KalmanStrategy:
    """Height, gradient and a Gauss-Markov curvature (std `sigma` um/tile^2, order 2)."""
    model = GaussMarkovModel(
        2,
        sigma,
        beta_per_tile,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
    )
    return KalmanStrategy(settings, model, name="kf-gm2", max_retries=max_retries)


def kf_wiener1_dir(
    settings: SlideSettings,
    *,
    q: float = 1e-4,
    q_height_um2: float = 0.0,
    slope_sigma_um_per_tile: float = 0.5,
    partitioned: bool = False,
    max_retries: int = 3,
) -> KalmanStrategy:
    """The direction-aware first-order filter (thesis eq. 3-54, 3-55, Algorithm 2)."""
    model = DirectionAwareModel(
        q,
        q_height_um2=q_height_um2,
        slope_sigma_um_per_tile=slope_sigma_um_per_tile,
        partitioned=partitioned,
    )
    return KalmanStrategy(settings, model, name="kf-wiener1-dir", max_retries=max_retries)


STRATEGIES: dict[str, Callable[..., Strategy]] = {
    "kf-wiener0": kf_wiener0,
    "kf-wiener1": kf_wiener1,
    "kf-wiener2": kf_wiener2,
    "kf-gm1": kf_gm1,
    "kf-gm2": kf_gm2,
    "kf-wiener1-dir": kf_wiener1_dir,
}
