"""`kf-rescan`: a slide scanned again, the last pass's map its prior, the drift estimated.

Slides are scanned again (time-lapse, a second channel, a higher magnification).
What changes between passes is mostly a slow drift of the whole slide (thermal,
mechanical: the HISP drift-estimation seed), plus a little local change. So the
height of tile (r, c) at time t is modelled as

    z(r, c, t) = b(r, c) + d(t) + l(r, c),

b the previous pass's map (its smoothed estimate, with its sigma), l an
independent local change of std `local_sigma_um`, and d the drift, whose state
is [offset um, rate um/s]: the rate a random walk of spectral density
`rate_q_um2_per_s3`, the offset integrating it (the continuous white-noise
acceleration model, Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]), plus, with
`offset_q_um2_per_s`, a random walk of the offset itself (q_o dt on P_dd): a thermal
drift wanders in its offset, and the last pass's own walk, held in its map along the
serpentine, comes back along this pass's (an integrated walk lags such a drift over
runs of unmeasured tiles: the rule sees no growing sigma). A measurement z of a
tile gives the innovation y = z - b - d with S = P_dd + sigma_b^2 + sigma_l^2 + R,
which corrects the drift state (gain P[:, 0] / S) and the tile's height
(prior variance V = P_dd + sigma_b^2 + sigma_l^2, the scalar update).

Time is the scan's own: every acquisition advances a clock by the timing
model's stage move and frames (`focustrack_core.timing`, the simulator's), so
the strategy stays a function of its measurement log.

The first tile knows nothing of the drift since the last pass (`start_sigma_um`):
its stack is coarse (`lean.coarse_stack`, the whole uncertainty in a few
frames), and the peak found there only centres a fine stack on the same tile,
which measures it; after that the lean rule (`lean.choose_stack`, default risk 1%)
takes the kept image alone on nearly every tile, measuring with 3 frames when
the drift's uncertainty has grown past the risk.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import Field, Strict

from focustrack_core.domain import SlideSettings
from focustrack_core.geometry import Tile
from focustrack_core.timing import TimingModel
from focustrack_estimator.filter_params import FilterParams, MaxKeptPlanes, RiskOutOfFocus
from focustrack_estimator.kalman_strategies import path_cost
from focustrack_estimator.lean_scan import DEFAULT_RISK, MAX_KEPT_PLANES
from focustrack_estimator.serpentine import Gaussian, SerpentineFilter
from focustrack_estimator.strategy import Z_LIMIT_UM, StrategyEntry
from focustrack_estimator.time_state import ScanClock

#: The sigma of a prior map given without one (um).
DEFAULT_MAP_SIGMA_UM = 0.05


#: Lists of numbers, as the REST API's parameters are (any length, possibly empty), each
#: within the API's bound on every height (as `PUT /prior`'s .npy map).
Heights = Annotated[
    tuple[Annotated[float, Field(ge=-Z_LIMIT_UM, le=Z_LIMIT_UM)], ...], Strict(False)
]
#: A sigma of zero would claim a tile's height exactly known (its gain 0 with no local change).
Sigmas = Annotated[tuple[Annotated[float, Field(gt=0.0, le=Z_LIMIT_UM)], ...], Strict(False)]


class KfRescanParams(FilterParams):
    """kf-rescan: the last pass's map as the prior, the drift since then estimated; tiles
    acquired by the lean rule (at most 1% out of focus by default)."""

    risk_out_of_focus: RiskOutOfFocus = DEFAULT_RISK
    max_kept_planes: MaxKeptPlanes = MAX_KEPT_PLANES
    prior_map_um: Heights = Field(
        (),
        description="The last pass's map: rows x cols heights, um, row after row (none: a "
        "flat map as unsure as the start, a scan that only tracks the drift)",
    )
    prior_map_sigma_um: Sigmas = Field(
        (),
        description="Its sigma, um, each positive: a map likewise, or one for every tile (none: "
        f"{DEFAULT_MAP_SIGMA_UM} um, what kf-2d's smoothed map has on the demo slide)",
    )
    local_sigma_um: float = Field(
        0.05, ge=0.0, description="Std of the local change of a tile between passes, um"
    )
    rate_sigma_um_per_s: float = Field(
        0.05, ge=0.0, description="Prior std of the drift's rate, um/s"
    )
    rate_q_um2_per_s3: float = Field(
        1e-6,
        ge=0.0,
        description="Spectral density of the random walk of the drift's rate, um^2/s^3",
    )
    offset_q_um2_per_s: float = Field(
        0.0,
        ge=0.0,
        description="Spectral density of a random walk of the drift's offset itself, um^2/s "
        "(a drift that wanders, as a thermal one does, and the last pass's own drift held in "
        "its map; 0: none, the offset only integrates the rate)",
    )


class RescanFilter(SerpentineFilter):
    """The previous pass's map plus a drift [offset, rate] and local change (module docstring).

    `start_z_um` and `start_sigma_um` of the slide are the drift's offset since the last
    pass and its uncertainty. Without a prior map every tile is as uncertain as the start
    (a flat map of sigma `start_sigma_um`): a scan that only tracks the drift.
    """

    name = "kf-rescan"

    def __init__(
        self, settings: SlideSettings, params: KfRescanParams, timing: TimingModel | None = None
    ) -> None:
        super().__init__(settings, params)
        self.base_um, base_sigma_um = prior_map(settings, params)
        self.base_var_um2 = np.square(base_sigma_um)
        self.local_var_um2 = params.local_sigma_um**2
        self.rate_q_um2_per_s3 = params.rate_q_um2_per_s3
        self.offset_q_um2_per_s = params.offset_q_um2_per_s
        self.clock = ScanClock(timing)
        # drift state [offset um, rate um/s] and its covariance, at time _state_s
        self.x = np.array([settings.start_z_um, 0.0])
        self.P = np.diag([settings.start_sigma_um**2, params.rate_sigma_um_per_s**2])
        self._state_s = 0.0
        self._step_var_um2 = 0.0  # the current tile's own step, let through the gate

    @property
    def drift_um(self) -> float:
        """The drift's offset now (um): the last pass's map plus this is the slide."""
        return float(self.x[0])

    @property
    def drift_um_per_s(self) -> float:
        """The drift's rate estimated so far."""
        return float(self.x[1])

    def _tile_var_um2(self, tile: Tile) -> float:
        return self.base_var_um2[tile.row, tile.col] + self.local_var_um2

    def _predict(self, tile: Tile) -> Gaussian:
        t_s = self.clock.arrival_s(self.grid, tile)
        dt = t_s - self._state_s
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Q = self.rate_q_um2_per_s3 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        Q[0, 0] += self.offset_q_um2_per_s * dt
        self.x, self.P, self._state_s = F @ self.x, F @ self.P @ F.T + Q, t_s
        mean_um = self.base_um[tile.row, tile.col] + self.x[0]
        return Gaussian(float(mean_um), float(self.P[0, 0] + self._tile_var_um2(tile)))

    def _inflate(self, var_um2: float) -> None:
        """A step the gate lets through (a fold, a moved section) is the tile's own change,
        not the drift's: it widens this tile's local variance alone, so the drift takes
        little of it."""
        self._step_var_um2 = var_um2

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        tile_var_um2, self._step_var_um2 = prior.var_um2 + self._step_var_um2, 0.0
        if z_um is None:
            return prior
        y = z_um - prior.mean_um
        S = tile_var_um2 + R_um2
        gain = self.P[:, 0] / S  # the drift's share of the innovation
        self.x = self.x + gain * y
        self.P = self.P - np.outer(gain, self.P[0, :])
        k = tile_var_um2 / S  # the tile's height: drift, prior map and local change together
        return Gaussian(prior.mean_um + k * y, tile_var_um2 * (1.0 - k))


def prior_map(settings: SlideSettings, params: KfRescanParams) -> tuple[np.ndarray, np.ndarray]:
    """The last pass's map and its sigma (rows, cols), um, from the flat lists of `params`;
    a ValueError if they do not fit the grid."""
    shape = settings.grid.shape
    if len(params.prior_map_um) == 0:
        return np.zeros(shape), np.full(shape, settings.start_sigma_um)
    base_um = np.asarray(params.prior_map_um, dtype=float)
    sigma = np.asarray(params.prior_map_sigma_um or [DEFAULT_MAP_SIGMA_UM], dtype=float)
    if base_um.size != math.prod(shape) or sigma.size not in (1, base_um.size):
        raise ValueError(
            f"the prior map must hold rows x cols = {math.prod(shape)} heights (and as "
            f"many sigmas, or one), got {base_um.size} and {sigma.size}"
        )
    base_sigma_um = np.broadcast_to(sigma.reshape(-1), base_um.size).reshape(shape).copy()
    return base_um.reshape(shape), base_sigma_um


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    # a few numbers per tile, as a 1-D filter keeps
    "kf-rescan": StrategyEntry(KfRescanParams, RescanFilter, path_cost(1)),
}
