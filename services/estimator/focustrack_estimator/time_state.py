"""The time state of the Kalman strategies: focus(x, y, t) = surface(x, y) + drift(t).

A stage and objective warm up while a slide is scanned; focus drifts by a few um
over tens of minutes. The filters model the surface over space; this module adds
the instrument's drift over time, estimated jointly with the surface (the
object-and-sensor idea of the HISP drift seed): two states appended to a filter's
state,

    [d, r]: the drift since the scan began (um) and its rate (um/s),

with d' = r + w_d and r' = -r / tau + w_r. The rate decays with time constant
`drift_settle_tau_s`, so an unknown initial rate (std `drift_rate_sigma_um_per_s`)
integrates to an exponential settling, d(t) = r0 tau (1 - exp(-t/tau)); w_d is a
random walk of the drift itself (spectral density `drift_walk_um2_per_s`), w_r a
slow random walk of the rate (`drift_rate_q_um2_per_s3`). d starts at 0 with no
uncertainty: the surface's own offset holds where the scan began, so the two are
told apart by time (revisits, rows, the settling's shape). Every tile's height is
measured as its surface plus d (H gains a 1 at d).

Time is the scan's own: `ScanClock` advances by the stage move and the frames of
each acquisition (`focustrack_core.timing.TimingModel`, the simulator's), so a
strategy stays a function of its measurement log. With every drift parameter at 0
(the default) the filters carry no time state at all and their results are those
of the surface model alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from focustrack_core.geometry import ScanGrid, Tile
from focustrack_core.timing import TimingModel
from focustrack_estimator.strategy import StrategyParams

#: States the time state appends to a filter: the drift (um) and its rate (um/s).
N_DRIFT = 2


class TimeStateParams(StrategyParams):
    """The drift of the instrument over time, estimated with the surface (all 0: off)."""

    drift_walk_um2_per_s: float = Field(
        0.0,
        ge=0.0,
        description="Spectral density of the random walk of the focus drift, um^2/s "
        "(0.0015: 0.3 um std after one minute). 0 with a rate sigma of 0: no time state",
    )
    drift_rate_sigma_um_per_s: float = Field(
        0.0,
        ge=0.0,
        description="Prior std of the drift's rate at the scan's start (the warm-up "
        "settling), um/s",
    )
    drift_settle_tau_s: float = Field(
        200.0, gt=0.0, description="Time constant of the settling: the rate decays by 1/e, s"
    )
    drift_rate_q_um2_per_s3: float = Field(
        0.0, ge=0.0, description="Spectral density of the random walk of the drift's rate, um^2/s^3"
    )


class RevisitParams(TimeStateParams):
    """The time state and revisits (`kf-2d`'s family: `spatial.RowBankFilter._revisit`)."""

    revisit_drift_share: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="With a time state and a stated risk: where the drift holds at least this "
        "share of a tile's predicted variance and the tile could not be imaged unmeasured, a "
        "tile measured before nearby is measured again first (purpose revisit: a stage move "
        "and a short stack) to pin the drift down (0: never)",
    )
    revisit_max_tiles: int = Field(
        3, ge=1, description="How far back along the row a revisited tile may lie, tiles"
    )


@dataclass(frozen=True)
class DriftModel:
    """The [drift, rate] states' transition over a time step (see the module docstring)."""

    walk_um2_per_s: float
    rate_sigma_um_per_s: float
    settle_tau_s: float
    rate_q_um2_per_s3: float = 0.0

    @classmethod
    def of(cls, params: object) -> DriftModel | None:
        """The model `params` state, None where they hold none or all of it is 0 (off)."""
        if not isinstance(params, TimeStateParams):
            return None
        moves = (
            params.drift_walk_um2_per_s,
            params.drift_rate_sigma_um_per_s,
            params.drift_rate_q_um2_per_s3,  # alone: a rate that starts at 0 and walks
        )
        if not any(moves):
            return None
        return cls(
            params.drift_walk_um2_per_s,
            params.drift_rate_sigma_um_per_s,
            params.drift_settle_tau_s,
            params.drift_rate_q_um2_per_s3,
        )

    def initial_covariance(self) -> np.ndarray:
        """P0 (2, 2) of the drift states, which start at 0: no drift yet, the rate unknown."""
        return np.diag([0.0, self.rate_sigma_um_per_s**2])

    def transition(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """F (2, 2) and Q (2, 2) over `dt_s` seconds.

        F = [[1, tau (1 - e)], [0, e]], e = exp(-dt/tau). Q: the walk q_d dt at the
        drift, and the rate's walk q_r through the same decay (integrated exactly:
        Q_rr = q_r tau (1 - e^2) / 2, the others to first order in its effect).
        """
        tau = self.settle_tau_s
        e = math.exp(-dt_s / tau)
        F = np.array([[1.0, tau * (1.0 - e)], [0.0, e]])
        q_rr = self.rate_q_um2_per_s3 * tau * (1.0 - e * e) / 2.0
        Q = np.array(
            [
                [self.walk_um2_per_s * dt_s + q_rr * dt_s**2 / 3.0, q_rr * dt_s / 2.0],
                [q_rr * dt_s / 2.0, q_rr],
            ]
        )
        return F, Q


class ScanClock:
    """The scan's time in s: each acquisition's stage move and frames (`TimingModel`).

    `arrival_s(grid, tile)` is when an acquisition on `tile` would start (after the move
    from the last tile); `advance` books an acquisition of `n_frames` frames there.
    """

    def __init__(self, timing: TimingModel | None = None) -> None:
        self.timing = timing or TimingModel()
        self.clock_s = 0.0  # the end of the last acquisition, s since the scan began
        self.here: Tile | None = None

    def arrival_s(self, grid: ScanGrid, tile: Tile) -> float:
        """When the next acquisition on `tile` starts: the clock plus the move there, s."""
        if self.here is None:
            return self.clock_s
        return self.clock_s + self.timing.move_s(grid.distance_um(self.here, tile))

    def advance(self, grid: ScanGrid, tile: Tile, n_frames: int) -> None:
        """Book an acquisition of `n_frames` frames on `tile`."""
        self.advance_by(grid, tile, self.timing.stack_s(n_frames))

    def advance_by(self, grid: ScanGrid, tile: Tile, seconds: float) -> None:
        """Book the move to `tile` and `seconds` there (a laser reading: no frames)."""
        self.clock_s = self.arrival_s(grid, tile) + seconds
        self.here = tile


def elapse(x: np.ndarray, P: np.ndarray, drift: DriftModel, first: int, dt_s: float) -> None:
    """Move the drift states x[..., first:first+2] and their covariance on by `dt_s`, in place.

    `x` (..., n) and `P` (..., n, n): one filter or a stack of them (a bank's members).
    Only the drift's rows and columns change: F P F' with F the identity elsewhere.
    """
    if dt_s <= 0:
        return
    F, Q = drift.transition(dt_s)
    d = slice(first, first + N_DRIFT)
    x[..., d] = x[..., d] @ F.T
    P[..., d, :] = F @ P[..., d, :]
    P[..., :, d] = P[..., :, d] @ F.T
    P[..., d, d] += Q
