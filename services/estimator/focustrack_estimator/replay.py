"""Replay a focus map through a strategy: the engine of `focustrack bench accuracy`.

Pure: no I/O. A strategy is driven through its two calls exactly as the
estimator service and the scheduler drive it; the instrument and the focus
service are stood in for by a measured map:

- the best focus found in a stack on tile (row, col) is `measured_um[row, col]`
  (the truth plus the focus method's error), the same value every time the tile
  is measured, so every strategy sees the same measurements;
- if that peak lies outside the acquired z-range, the stack has no peak inside:
  the measurement is an edge flag pointing towards it, and the strategy must
  re-acquire (and pay for it);
- a single-frame acquisition only images the tile (no measurement);
- a revisit (purpose revisit: a tile measured again, to track the drift) is a new
  measurement: the truth plus the drift now plus its own noise (the slide's
  `noise_sigma_um`, drawn per acquisition), and it leaves the tile's image as it was;
- with a `FrameCheck` (a second pass's first-frame check, as the scheduler's
  `focus_check` makes it), a tile imaged once at its prediction without a measurement
  is posted `frame_out_of_focus` where the check finds its frame so;
- a laser reading (purpose laser) is `ReplayLaser`'s: the coverslip under the tile
  (the truth plus the drift now minus the tile's offset) with the laser's noise; it
  takes no frame, only the move and the reading's time.

Cost follows `focustrack_core.timing.TimingModel`: the XY move from the previous
acquisition's tile, then the stack's frames. The physical limit of a scan
(`limit_time_s`) is the serpentine's stage moves plus one exposure per tile (the
kept image), with no search at all.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    kept_in_focus,
)
from focustrack_core.geometry import ScanGrid, Tile
from focustrack_core.laser import LaserSpec, laser_reading
from focustrack_core.timing import TimingModel
from focustrack_estimator.lean import out_of_focus_risk
from focustrack_estimator.strategy import Strategy


def simulated_measurement(acquisition: Acquisition, measured_um: float) -> Measurement:
    """What a focus service would report for `acquisition` if the peak is at `measured_um`."""
    if not acquisition.measure:
        return Measurement(z_um=None)
    if measured_um < acquisition.z.low_um:
        return Measurement(z_um=None, flags=frozenset({FocusFlag.EDGE_LOW}))
    if measured_um > acquisition.z.high_um:
        return Measurement(z_um=None, flags=frozenset({FocusFlag.EDGE_HIGH}))
    return Measurement(z_um=float(measured_um))


@dataclass
class Replay:
    """One strategy's scan of one map."""

    truth_um: np.ndarray  # (rows, cols)
    focus_map: FocusMap
    outcomes: list[Outcome]
    n_images: int
    scan_time_s: float
    limit_time_s: float  # stage moves along the serpentine plus one frame per tile
    # tiles that keep several frames (`Outcome.planes_um`): (row, col) -> their z, in um
    planes_um: dict[tuple[int, int], tuple[float, ...]]
    n_revisits: int = 0  # acquisitions of purpose revisit
    n_laser_readings: int = 0  # acquisitions of purpose laser

    def in_focus(self, dof_um: float) -> np.ndarray:
        """(rows, cols) bool: a frame the tile keeps lies within dof/2 of its truth."""
        inside = np.abs(self.focus_map.z_used_um - self.truth_um) <= dof_um / 2.0
        for (row, col), planes_um in self.planes_um.items():
            inside[row, col] = kept_in_focus(planes_um, self.truth_um[row, col], dof_um)
        return inside

    @property
    def frames_kept(self) -> int:
        """Frames kept over all tiles imaged (one per tile, more where it keeps planes)."""
        imaged = int(np.isfinite(self.focus_map.z_used_um).sum())
        return imaged + sum(len(planes) - 1 for planes in self.planes_um.values())


def limit_time_s(grid: ScanGrid, timing: TimingModel) -> float:
    """The fastest scan of `grid` in s: the serpentine's moves and one frame per tile."""
    path = grid.serpentine
    moves_s = sum(timing.move_s(grid.distance_um(a, b)) for a, b in itertools.pairwise(path))
    return moves_s + grid.n_tiles * timing.stack_s(1)


@dataclass(frozen=True)
class ReplayLaser:
    """The laser autofocus of a replay: each tile's offset from the coverslip to the tissue's
    focal plane, (rows, cols) um (`focustrack_core.laser.coverslip_offsets`), and the sensor."""

    offsets_um: np.ndarray
    spec: LaserSpec


class DriftPath(Protocol):
    """The whole slide's z drift over a scan: `at(t_s)` in um, t_s seconds into the scan."""

    def at(self, t_s: float) -> float: ...


@dataclass(frozen=True)
class Drift:
    """The whole slide moving in z while it is scanned: offset_um + rate_um_per_s * t."""

    offset_um: float
    rate_um_per_s: float

    def at(self, t_s: float) -> float:
        """The drift (um) t_s seconds into the scan."""
        return self.offset_um + self.rate_um_per_s * t_s


class FrameCheck(Protocol):
    """A second pass's first-frame check: whether tile (row, col)'s one frame at `z_um` is
    found out of focus, its true focus then at `truth_um` (um)."""

    def __call__(self, row: int, col: int, z_um: float, truth_um: float) -> bool: ...


def replay(
    strategy: Strategy,
    truth_um: np.ndarray,
    measured_um: np.ndarray,
    timing: TimingModel | None = None,
    drift: DriftPath | None = None,
    laser: ReplayLaser | None = None,
    frame_check: FrameCheck | None = None,
) -> Replay:
    """Run `strategy` to completion on one map; `truth_um` and `measured_um` are (rows, cols).

    With `drift`, the slide moves while it is scanned (a re-scan): a stack sees
    the measured map plus the drift at the stack's start on the scan's clock, and
    the truth a tile is scored on is its height when its last stack started (the
    `Replay.truth_um`). `drift` may be any `DriftPath` (`focustrack_core.drift.ThermalDrift`).
    `laser` answers a strategy's laser readings (a ValueError where one is asked without it).
    `frame_check` checks each frame a tile is imaged with unmeasured (module docstring).
    """
    timing = timing or TimingModel()
    drift = drift or Drift(0.0, 0.0)
    grid = strategy.grid
    if truth_um.shape != grid.shape or measured_um.shape != grid.shape:
        raise ValueError(
            f"map shapes {truth_um.shape} / {measured_um.shape} differ from grid {grid.shape}"
        )
    max_acquisitions = 50 * grid.n_tiles  # a strategy that never finishes is a bug, not a slow scan
    outcomes: list[Outcome] = []
    n_images, scan_time_s, n_revisits, n_laser = 0, 0.0, 0, 0
    here: Tile | None = None
    truth_now_um = truth_um.astype(float)  # each tile's truth when its last stack started
    while (acquisition := strategy.next_acquisition()) is not None:
        if len(outcomes) >= max_acquisitions:
            raise RuntimeError(f"{strategy.name} did not finish in {max_acquisitions} acquisitions")
        tile = Tile(acquisition.row, acquisition.col)
        if here is not None:
            scan_time_s += timing.move_s(grid.distance_um(here, tile))
        here = tile
        drift_um = drift.at(scan_time_s)
        if acquisition.purpose is Purpose.LASER:
            if laser is None:
                raise ValueError(f"{strategy.name} asks for laser readings: give replay a laser")
            n_laser += 1
            scan_time_s += laser.spec.reading_s
            reading_um = laser_reading(
                truth_um[tile.row, tile.col] + drift_um,
                laser.offsets_um[tile.row, tile.col],
                laser.spec.noise_um,
                np.random.default_rng([acquisition.index, 9]),
            )
            reading = Measurement(z_um=reading_um, sigma_um=laser.spec.noise_um or None)
            outcomes.append(strategy.record(acquisition, reading))
            continue
        n_images += acquisition.z.n_frames
        scan_time_s += timing.stack_s(acquisition.z.n_frames)
        if acquisition.purpose is Purpose.REVISIT:
            n_revisits += 1
            noise_um = np.random.default_rng([acquisition.index, 5]).standard_normal()
            noise_um *= strategy.settings.noise_sigma_um
            measured = truth_um[tile.row, tile.col] + drift_um + noise_um
        else:
            truth_now_um[tile.row, tile.col] = truth_um[tile.row, tile.col] + drift_um
            measured = measured_um[tile.row, tile.col] + drift_um
        measurement = simulated_measurement(acquisition, measured)
        if (
            frame_check is not None
            and not acquisition.measure
            and acquisition.purpose is Purpose.SCAN
            and frame_check(
                tile.row, tile.col, acquisition.z.center_um, truth_now_um[tile.row, tile.col]
            )
        ):
            measurement = dataclasses.replace(measurement, frame_out_of_focus=True)
        outcomes.append(strategy.record(acquisition, measurement))
    return Replay(
        truth_now_um,
        strategy.focus_map(),
        outcomes,
        n_images,
        scan_time_s,
        limit_time_s(grid, timing),
        {(o.row, o.col): o.planes_um for o in outcomes if o.planes_um},
        n_revisits,
        n_laser,
    )


@dataclass(frozen=True)
class Scores:
    """Accuracy and cost of a strategy over several maps (errors pooled over all tiles).

    `*_std_um` is the standard deviation of the signed error (as in the thesis'
    tables); prior fields are None for strategies that make no prediction.
    """

    prior_mae_um: float | None
    prior_std_um: float | None
    post_mae_um: float
    post_std_um: float
    images_per_tile: float
    scan_time_s: float  # mean per map
    in_focus_fraction: float
    limit_time_s: float  # mean per map: moves plus one frame per tile (`limit_time_s`)
    frames_kept_per_tile: float  # 1, more where tiles keep several frames (`Replay.planes_um`)


#: Bins of predicted out-of-focus risk for the reliability table (`reliability`).
RISK_BINS = (0.0, 0.001, 0.01, 0.05, 0.2, 0.5, 1.0)


@dataclass(frozen=True)
class RiskBin:
    """Tiles whose predicted risk lies in [low, high): how many, predicted and achieved."""

    low: float
    high: float
    n_tiles: int
    predicted: float  # mean predicted risk of these tiles
    achieved: float  # share of them imaged outside the depth of field


def predicted_risk(run: Replay, dof_um: float) -> np.ndarray:
    """Each tile's predicted P(out of focus), (rows, cols): the truth outside the depth of
    field of every frame the tile keeps (`Replay.in_focus`).

    The strategy's own (`FocusMap.out_of_focus_risk`) where it states one, else the
    Gaussian of its posterior (its prior where it did not measure) about the kept frame.
    """
    fm = run.focus_map
    gaussian = out_of_focus_risk(fm.posterior_um, fm.posterior_sigma_um, fm.z_used_um, dof_um)
    if fm.out_of_focus_risk is None:
        return gaussian
    return np.where(np.isfinite(fm.out_of_focus_risk), fm.out_of_focus_risk, gaussian)


def reliability(replays: list[Replay], dof_um: float) -> list[RiskBin]:
    """Predicted against achieved out-of-focus rate, binned by predicted risk (`RISK_BINS`)."""
    risk = np.concatenate([predicted_risk(r, dof_um).ravel() for r in replays])
    out = np.concatenate([~r.in_focus(dof_um).ravel() for r in replays])
    bins = []
    for low, high in itertools.pairwise(RISK_BINS):
        inside = (risk >= low) & ((risk < high) if high < 1.0 else (risk <= high))
        if inside.any():
            bins.append(
                RiskBin(
                    low,
                    high,
                    int(inside.sum()),
                    float(risk[inside].mean()),
                    float(out[inside].mean()),
                )
            )
    return bins


def _error_stats(estimates: list[np.ndarray], truths: list[np.ndarray]) -> tuple[float, float]:
    error = np.concatenate([(e - t).ravel() for e, t in zip(estimates, truths, strict=True)])
    return float(np.mean(np.abs(error))), float(np.std(error))


def score(replays: list[Replay], dof_um: float) -> Scores:
    """Pool one strategy's replays into its scores (in focus: `Replay.in_focus`)."""
    truths = [r.truth_um for r in replays]
    priors = [r.focus_map.prior_um for r in replays]
    has_prior = all(np.all(np.isfinite(p)) for p in priors)
    prior_mae, prior_std = _error_stats(priors, truths) if has_prior else (None, None)
    post_mae, post_std = _error_stats([r.focus_map.posterior_um for r in replays], truths)
    n_tiles = sum(r.truth_um.size for r in replays)
    return Scores(
        prior_mae_um=prior_mae,
        prior_std_um=prior_std,
        post_mae_um=post_mae,
        post_std_um=post_std,
        images_per_tile=sum(r.n_images for r in replays) / n_tiles,
        scan_time_s=float(np.mean([r.scan_time_s for r in replays])),
        in_focus_fraction=float(
            np.mean(np.concatenate([r.in_focus(dof_um).ravel() for r in replays]))
        ),
        frames_kept_per_tile=sum(r.frames_kept for r in replays) / n_tiles,
        limit_time_s=float(np.mean([r.limit_time_s for r in replays])),
    )
