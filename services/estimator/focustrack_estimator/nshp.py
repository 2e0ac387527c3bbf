"""The NSHP filters, `nshp-wiener0` and `nshp-wiener1`: 2-D estimators over heights.

The thesis' Non-Symmetric Half-Plane filter (ch. 4, eq. 4-1 to 4-4, Algorithm 3)
with the two causes of its failure (section 4-2-4) removed. The state holds
heights only, so the y-gradient is implied by measured heights instead of
carried as a state that is never observed; and the state's every element is
corrected with the full Kalman gain and propagated with its full covariance, so
the prediction uses the neighbours' estimates with their correct
(cross-)covariances rather than as if they were noise-free inputs (no
"K[slc] = 0", Algorithm 3 line 13). They run the one per-tile loop of every
filter strategy (`serpentine.SerpentineFilter`); `spatial` has the other 2-D
estimator, `kf-2d` (docs/spatial.md). Heights in um, lengths in tiles.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from focustrack_core.domain import SlideSettings
from focustrack_core.geometry import Tile
from focustrack_estimator.filter_params import RetryParams
from focustrack_estimator.serpentine import Gaussian, SerpentineFilter
from focustrack_estimator.sqrt_filter import SqrtKalmanFilter
from focustrack_estimator.strategy import NOMINAL_FLOPS_PER_S, Cost, StrategyEntry, tile_cost


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
        self, settings: SlideSettings, params: NshpParams, *, name: str, order: int
    ) -> None:
        super().__init__(settings, params)
        self.name = name
        self.order, self.support, self.q_um2 = order, params.support, params.q_um2
        self._tiles: list[Tile] = []  # the tile of each state element
        self._kf = SqrtKalmanFilter(dim_x=1, dim_z=1)

    def _support(self, tile: Tile) -> list[Tile]:
        """The already-scanned NSHP neighbours of `tile` (eq. 4-1 with M1 = M2 = M)."""
        # M clipped to the grid: a support wider than the slide reaches every tile, and its
        # candidates are enumerated in the grid's size, not in M^2 (M may be 10^9)
        rows_up = min(self.support, tile.row)
        left, right = min(self.support, tile.col), min(self.support, self.grid.cols - 1 - tile.col)
        behind = -1 if tile.row % 2 == 0 else 1  # serpentine: even rows go left to right
        row_reach = left if behind < 0 else right
        candidates = [Tile(tile.row, tile.col + behind * k) for k in range(1, row_reach + 1)]
        candidates += [
            Tile(tile.row - k, tile.col + d)
            for k in range(1, rows_up + 1)
            for d in range(-left, right + 1)
        ]
        return candidates

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


# Defaults chosen on training seeds 0..9 (docs/spatial.md), never on the reported maps.

Support = Annotated[
    int,
    Field(
        ge=1,
        description="M of the support (thesis eq. 4-1): the M tiles behind on the row and M "
        "rows above, from M columns back to M ahead, tiles",
    ),
]
QUm2 = Annotated[
    float,
    Field(gt=0.0, description="Variance of the noise added to each tile's predicted height, um^2"),
]


class NshpParams(RetryParams):
    """An NSHP filter's parameters (each strategy has its defaults)."""

    support: Support
    q_um2: QUm2


class NshpWiener0Params(NshpParams):
    """nshp-wiener0: the weighted mean of the support heights, plus noise."""

    support: Support = 1
    q_um2: QUm2 = 0.5


class NshpWiener1Params(NshpParams):
    """nshp-wiener1: the support's weighted plane extrapolated to the tile, plus noise."""

    support: Support = 2
    q_um2: QUm2 = 0.03


def nshp_wiener0(settings: SlideSettings, params: NshpWiener0Params) -> NshpFilter:
    """NSHP filter, order 0: the weighted mean of the support heights, plus noise."""
    return NshpFilter(settings, params, name="nshp-wiener0", order=0)


def nshp_wiener1(settings: SlideSettings, params: NshpWiener1Params) -> NshpFilter:
    """NSHP filter, order 1: the support's weighted plane extrapolated to the tile, plus noise."""
    return NshpFilter(settings, params, name="nshp-wiener1", order=1)


def nshp_cost(settings: SlideSettings, params: NshpParams) -> Cost:
    """NSHP: the state holds `support` rows and the current one; every tile re-factors its
    square-root covariance (a QR of a 2 dim x dim matrix, about 5 dim^3 operations); fitted
    like kf-2d's (`spatial.kf_2d_cost`)."""
    rows, cols = settings.grid.shape
    dim = min(rows, params.support + 1) * cols
    # P's square root, the dense F of the step and the QR's stacked input and output.
    return tile_cost(settings) + Cost(8 * 10 * dim * dim, 5 * dim**3 / NOMINAL_FLOPS_PER_S)


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "nshp-wiener0": StrategyEntry(NshpWiener0Params, nshp_wiener0, nshp_cost),
    "nshp-wiener1": StrategyEntry(NshpWiener1Params, nshp_wiener1, nshp_cost),
}
