"""Checks of a strategy restored from a snapshot, before it is served: pure, no I/O.

A snapshot's checksum (`event_store.snapshot_digest`) shows that it is what was
stored; these checks show that what it holds makes sense for the slide, whoever
wrote it: the state stands for the number of events it claims, its map has the
slide's grid shape, finite heights within bounds and sigmas and risks in range,
the acquisition it would ask for next lies on the grid at a height a stack may
reach, and the last event it covers reads back from it as logged. A state that
fails any of them raises `SnapshotError` (`Slide.load` then rebuilds the slide
from its log, the source of truth).
"""

from __future__ import annotations

import math

import numpy as np

from focustrack_core.domain import Acquisition, FocusMap, Outcome, SlideSettings
from focustrack_estimator.records import REPLAY_TOLERANCE
from focustrack_estimator.snapshot import SnapshotError
from focustrack_estimator.strategy import Z_LIMIT_UM, Strategy

#: Heights a restored map may hold, +/- um: twice the API's bound on every height (an
#: estimate may extrapolate beyond the heights measured, never that far).
MAP_LIMIT_UM = 2 * Z_LIMIT_UM

#: The map's layers of heights and of sigmas (um), each (rows, cols), NaN where none.
_HEIGHTS = ("prior_um", "posterior_um", "z_used_um", "smoothed_um")
_SIGMAS = ("prior_sigma_um", "posterior_sigma_um", "smoothed_sigma_um")

#: The fields of an outcome that the map holds at its tile after it (the posterior is not
#: among them: a survey strategy interpolates its map over the tiles it measured).
_READ_BACK = ("prior_um", "prior_sigma_um", "posterior_sigma_um")


def check_restored(
    strategy: Strategy, settings: SlideSettings, n_events: int, last: Outcome
) -> None:
    """Raise SnapshotError unless `strategy`, restored from a snapshot said to stand for the
    slide's first `n_events` events (the last of which had `last` as its outcome), fits the
    slide's `settings` (those of its configuration, not the snapshot's)."""
    if strategy.settings != settings or strategy.grid != settings.grid:
        raise SnapshotError("its settings or grid are not the slide's")
    if strategy.n_recorded != n_events:
        raise SnapshotError(f"it holds {strategy.n_recorded} events, not {n_events}")
    _check_map(strategy.map, settings)
    _check_read_back(strategy.map, last)
    pending = strategy.next_acquisition()
    if pending is not None:
        _check_pending(pending, settings, n_events)


def _check_map(focus_map: FocusMap, settings: SlideSettings) -> None:
    for name, layer in vars(focus_map).items():
        if layer is None:
            continue
        if not isinstance(layer, np.ndarray) or layer.shape != settings.grid.shape:
            shape = getattr(layer, "shape", type(layer).__name__)
            raise SnapshotError(f"its map's {name} is {shape}, not {settings.grid.shape}")
        if layer.dtype.kind != "f" or np.isinf(layer).any():
            raise SnapshotError(f"its map's {name} holds values that are not finite numbers")
        known = layer[~np.isnan(layer)]
        if name in _HEIGHTS and (np.abs(known) > MAP_LIMIT_UM).any():
            raise SnapshotError(f"its map's {name} holds heights beyond +/-{MAP_LIMIT_UM:g} um")
        if name in _SIGMAS and (known < 0).any():
            raise SnapshotError(f"its map's {name} holds negative sigmas")
        if name == "out_of_focus_risk" and ((known < 0) | (known > 1)).any():
            raise SnapshotError("its map's out_of_focus_risk holds values outside 0..1")


def _check_read_back(focus_map: FocusMap, last: Outcome) -> None:
    for name in _READ_BACK:
        logged = getattr(last, name)
        held = float(getattr(focus_map, name)[last.row, last.col])
        if logged is not None and not math.isclose(
            held, logged, rel_tol=REPLAY_TOLERANCE, abs_tol=REPLAY_TOLERANCE
        ):
            raise SnapshotError(
                f"its map's {name} at tile ({last.row}, {last.col}) is {held}, the log's {logged}"
            )


def _check_pending(pending: Acquisition, settings: SlideSettings, n_events: int) -> None:
    where = f"its next acquisition ({pending.index} at tile ({pending.row}, {pending.col}))"
    if pending.index != n_events:
        raise SnapshotError(f"{where} is not number {n_events}")
    if not settings.grid.contains(pending.row, pending.col):
        raise SnapshotError(f"{where} lies outside the {settings.grid.shape} grid")
    z = pending.z
    heights = (z.low_um, z.high_um, pending.predicted_um, pending.predicted_sigma_um)
    if not all(h is None or math.isfinite(h) for h in heights) or not math.isfinite(z.step_um):
        raise SnapshotError(f"{where} has heights that are not finite")
    limit_um = Z_LIMIT_UM + REPLAY_TOLERANCE  # `strategy.bounded` puts every stack inside
    if not -limit_um <= z.low_um <= z.high_um <= limit_um:
        raise SnapshotError(
            f"{where} spans {z.low_um:g}..{z.high_um:g} um, beyond +/-{Z_LIMIT_UM:g} um"
        )
