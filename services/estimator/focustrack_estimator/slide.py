"""One live slide: its strategy, rebuilt from its durable log, and the history of its scan.

A `Slide` pairs a strategy with the history of what it was asked and told. A new
slide is checked (`Slide.checked`) and stored; after a restart (or an eviction) a slide
is rebuilt from its store (`Slide.load`): from its newest snapshot (the strategy's
state, written every `snapshot_every` measurements, when the scan completes and at
shutdown) and the events logged after it, or from the whole log when there is no
snapshot that fits. Strategies are deterministic, so the replay gives back the same
state; it checks that every acquisition and outcome comes out as logged, and
tolerates differences of floating-point noise (another numpy or BLAS) with a
warning. The log stays the source of truth: a snapshot is used only if its checksum
matches (the store's check), its state fits the slide (`restored.check_restored`)
and the events after it replay from it; else it is discarded with a warning, the
slide rebuilt from its whole log and a new snapshot stored in its place. A log
record that fails its own checks (`CorruptLogError`) stops its slide alone. A
measurement is committed before its outcome is returned.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from typing import Any

from focustrack_client import models as api
from focustrack_core.domain import Acquisition, FocusMap, Measurement, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_domain
from focustrack_estimator import registry
from focustrack_estimator.budget import Budget, GridLimits
from focustrack_estimator.diagnose import SlideDiagnostics, diagnose
from focustrack_estimator.errors import (
    STRATEGY_ERRORS,
    ReplayMismatchError,
    SlideConflictError,
    SlideError,
    StrategyNotServedError,
)
from focustrack_estimator.event_store import (
    CorruptSnapshotError,
    Event,
    EventStore,
    SlideRecord,
    StoreError,
)
from focustrack_estimator.history import History
from focustrack_estimator.records import (
    Logged,
    acquisition_record,
    checked_logged_of,
    config_of,
    event_of,
    measurement_record,
    outcome_record,
    same_up_to_round_off,
)
from focustrack_estimator.restored import check_restored
from focustrack_estimator.slide_strategy import (
    cost_of,
    new_strategy,
    probe,
    resolved_params,
    served,
    stored_config,
)
from focustrack_estimator.snapshot import SnapshotError, encode, restore
from focustrack_estimator.strategy import Cost, StrategyParams

log = logging.getLogger(__name__)


def _untimed(_: float) -> None:
    """A timer that keeps nothing (a slide outside the service)."""


def _uncounted() -> None:
    """A count of discarded snapshots that keeps nothing (a slide outside the service)."""


class Slide:
    """One slide's live strategy and its history. Not thread-safe: `Slides` serialises calls.

    `timer` is called with the seconds spent in each strategy call (for /metrics).
    A snapshot of the strategy is stored every `snapshot_every` measurements
    and when the scan completes. `catalogue`: the strategies served (None: the
    estimator's own).
    """

    def __init__(
        self,
        slide_id: str,
        config: api.SlideCreate,
        params: StrategyParams,
        cost: Cost,
        store: EventStore,
        *,
        snapshot_every: int,
        timer: Callable[[float], None] = _untimed,
        catalogue: registry.Catalogue | None = None,
    ) -> None:
        self.id = slide_id
        self.config = config
        self.store = store
        self._timer = timer
        self.snapshot_every = snapshot_every
        self.history = History()
        self.n_snapshot = 0  # events covered by the newest snapshot stored
        self.restored = False  # True: the state came from a snapshot, not from the log alone
        self._snapshots = True  # False once the strategy's state proved impossible to store
        self.cost = cost  # its share of the live slides' budget
        start_s = time.perf_counter()
        self.strategy = new_strategy(config, params, served(catalogue))
        self._timer(time.perf_counter() - start_s)

    @classmethod
    def checked(
        cls,
        slide_id: str,
        config: api.SlideCreate,
        store: EventStore,
        *,
        limits: GridLimits,
        budget: Budget,
        snapshot_every: int,
        timer: Callable[[float], None] = _untimed,
        catalogue: registry.Catalogue | None = None,
    ) -> Slide:
        """A slide of `config`, checked (grid, budget, parameters, a trial scan), its
        parameters resolved (`self.config`), not stored: the caller stores it, as a new
        slide or as the new configuration of a slide whose log is empty; a SlideError says
        what is wrong."""
        strategies = served(catalogue)
        limits.check(config.grid)
        params = resolved_params(config, strategies)  # once, for all that follows
        cost = cost_of(config, params, strategies)
        budget.check(config, cost)
        config = stored_config(config, params)
        slide = cls(
            slide_id,
            config,
            params,
            cost,
            store,
            snapshot_every=snapshot_every,
            timer=timer,
            catalogue=strategies,
        )
        probe(config, params, strategies)
        return slide

    @classmethod
    def load(
        cls,
        record: SlideRecord,
        store: EventStore,
        *,
        snapshot_every: int,
        timer: Callable[[float], None] = _untimed,
        catalogue: registry.Catalogue | None = None,
        use_snapshot: bool = True,
        discarded: Callable[[], None] = _uncounted,
    ) -> Slide:
        """The stored slide of `record`, rebuilt from its newest snapshot and the events after
        it, or from its whole log (when there is no snapshot, or it fails its checks, or
        not `use_snapshot`: then its log's state replaces the stored snapshot). `discarded`
        is called for each snapshot found wanting. ReplayMismatchError if the log no
        longer replays, CorruptLogError if a record of it fails its own checks."""
        slide_id, config = record.id, config_of(record)
        strategies = served(catalogue)
        if config.strategy not in strategies.strategies:
            raise StrategyNotServedError(
                f"slide {slide_id} scans with strategy {config.strategy!r}, which this "
                "estimator does not serve: start it with the catalogue the slide was made "
                "under (--strategies-from MODULE); it serves "
                f"{', '.join(sorted(strategies.strategies))}"
            )
        try:
            params = resolved_params(config, strategies)
        except SlideError as error:  # stored as valid: this version's strategy refuses them
            raise ReplayMismatchError(
                f"slide {slide_id}: its stored parameters are refused by this version of "
                f"strategy {config.strategy!r}: {error}"
            ) from None
        cost = cost_of(config, params, strategies)

        def built() -> Slide:
            return cls(
                slide_id,
                config,
                params,
                cost,
                store,
                snapshot_every=snapshot_every,
                timer=timer,
                catalogue=catalogue,
            )

        slide = built()
        replace_snapshot = not use_snapshot
        if use_snapshot:
            try:
                slide._restore(record.n_events)
            except (SnapshotError, CorruptSnapshotError) as error:
                log.warning("slide %s: snapshot not used, replaying its log: %s", slide_id, error)
                discarded()
                slide, replace_snapshot = built(), True
        if not slide.restored:
            slide._replay(slide._read(0))
        # As `measure` leaves a live slide: its next acquisition asked for, which sets that
        # tile's prior in the map (a restarted service, or another replica, served none).
        slide.strategy.next_acquisition()
        if replace_snapshot:  # the log's state in the place of a snapshot found wanting
            slide.save_snapshot()
        return slide

    def _restore(self, n_logged: int) -> None:
        """Take the state of the slide's snapshot, if it has one, checked against the slide's
        configuration and log (of `n_logged` events), and replay the events after it; only
        those are read now (the others when first needed). SnapshotError or
        CorruptSnapshotError if the snapshot fails a check: the strategy is then
        half-written, to be discarded."""
        snapshot = self.store.snapshot(self.id)
        if snapshot is None:
            return
        if not 0 < snapshot.n_events <= n_logged:
            raise SnapshotError(f"it stands for {snapshot.n_events} events; the log has {n_logged}")
        settings = self.strategy.settings  # the configuration's, before the snapshot's
        restore(self.strategy, snapshot.state)
        events = self._read(snapshot.n_events - 1)  # the last event it covers, then the rest
        try:
            check_restored(self.strategy, settings, snapshot.n_events, events[0].outcome)
            self._cover_history(snapshot.n_events)
            self._replay(events[1:])
        except (ReplayMismatchError, *STRATEGY_ERRORS, LookupError) as error:
            raise SnapshotError(f"its state does not lead to the log's: {error}") from None
        self.n_snapshot = snapshot.n_events
        self.restored = True

    def _read(self, start: int) -> list[Logged]:
        """The slide's logged events from sequence `start` on, each checked
        (`records.checked_logged_of`: CorruptLogError naming the first that fails)."""
        events = self.store.events(self.id, start)
        return [
            checked_logged_of(self.id, event, start + i, self.grid)
            for i, event in enumerate(events)
        ]

    @property
    def grid(self) -> ScanGrid:
        return self.strategy.grid

    def next(self) -> Acquisition | None:
        start_s = time.perf_counter()
        acquisition = self.strategy.next_acquisition()
        self._timer(time.perf_counter() - start_s)
        return acquisition

    def _replay(self, events: list[Logged]) -> None:
        """Rebuild the state from the logged events, checking each comes out as logged.

        A replayed acquisition or outcome that differs from the logged one by
        round-off only (`same_up_to_round_off`) is logged as a warning and the
        replay goes on; the history keeps the logged records, which the
        clients were given. Any other difference is a ReplayMismatchError.
        """
        for logged in events:
            event = event_of(logged)
            acquisition = self.strategy.next_acquisition()
            replayed = None if acquisition is None else acquisition_record(acquisition)
            self._check(event, "acquisition", replayed, event.acquisition)
            assert acquisition is not None  # checked against the logged one
            outcome = self.strategy.record(acquisition, logged.measurement)
            self._check(event, "outcome", outcome_record(outcome), event.outcome)
            self.history.append(logged)

    def _check(self, event: Event, what: str, replayed: Any, logged: dict[str, Any]) -> None:
        if replayed == logged:
            return
        if replayed is not None and same_up_to_round_off(replayed, logged):
            log.warning(
                "slide %s: replayed %s %d differs from the logged one by round-off only "
                "(another numpy or BLAS?); going on. replayed %s, logged %s",
                self.id, what, event.sequence, replayed, logged,
            )  # fmt: skip
            return
        raise ReplayMismatchError(
            f"slide {self.id}: logged {what} {event.sequence} no longer replays "
            f"(the strategy {self.config.strategy!r} changed since it was logged)"
        )

    def _cover_history(self, n_events: int) -> None:
        """Take the first `n_events` logged events as the history without replaying them (a
        snapshot covers them); they are read from the store when first needed (`History`)."""

        def load() -> list[Logged]:
            return self._read(0)[:n_events]

        self.history = History(load, n_events)

    def save_snapshot(self) -> bool:
        """Store the strategy's state as the snapshot after the history's events; False
        if the store failed.

        Never fails the request: a state that cannot be encoded turns snapshots
        off for this slide (it is then rebuilt from its whole log), a store error
        leaves the older snapshot (the log has every event either way).
        """
        if not self._snapshots or len(self.history) <= self.n_snapshot:
            return True
        try:
            blob = encode(self.strategy)
            self.store.put_snapshot(self.id, len(self.history), blob)
        except SnapshotError as error:
            self._snapshots = False
            log.warning("slide %s: no snapshots for its strategy: %s", self.id, error)
            return True
        except StoreError as error:
            log.warning("slide %s: snapshot not stored: %s", self.id, error)
            return False
        self.n_snapshot = len(self.history)
        return True

    def measure(self, request: api.MeasurementIn) -> tuple[Logged, bool]:
        """Record a measurement (durably) or return the one already recorded for it.

        Returns the logged acquisition with its outcome, and whether it is new
        (False: an idempotent re-post).
        Raises SlideError (tile outside the grid), SlideConflictError (not the pending
        acquisition, a re-post with another value, the scan is complete), and the
        store's SequenceConflictError if another writer moved the log on.
        """
        tile = (request.row, request.col)
        if not self.grid.contains(*tile):
            raise SlideError(
                f"tile ({request.row}, {request.col}) is outside the slide's "
                f"{self.grid.rows}x{self.grid.cols} grid",
                ("body", "row" if request.row >= self.grid.rows else "col"),
            )
        try:
            measurement = to_domain.measurement(request)
        except ValueError as error:
            raise SlideError(str(error), ("body",)) from None
        if request.sequence < len(self.history):
            return self._recorded(request, measurement), False
        pending = self.next()
        if pending is None:
            raise SlideConflictError(
                f"the scan is complete: sequence {request.sequence} was not asked for"
            )
        if request.sequence != pending.index or tile != (pending.row, pending.col):
            raise SlideConflictError(
                f"acquisition {request.sequence} at tile ({request.row}, {request.col}) was "
                f"not asked for: the pending one is {pending.index} at tile "
                f"({pending.row}, {pending.col})"
            )
        if not pending.measure and measurement.z_um is not None:
            # A height for a tile that was only to be imaged would be dropped unseen.
            raise SlideError(
                f"acquisition {pending.index} only images tile ({pending.row}, {pending.col}) "
                "(measure: false): post z_um null, with frame_out_of_focus true if its frame "
                "was out of focus",
                ("body", "z_um"),
            )
        _check_within_reach(pending, measurement)
        start_s = time.perf_counter()
        outcome = self.strategy.record(pending, measurement)
        done = self.strategy.next_acquisition() is None
        self._timer(time.perf_counter() - start_s)
        logged = Logged(pending, measurement, outcome)
        self.store.append(self.id, event_of(logged), accepted=outcome.accepted, done=done)
        self.history.append(logged)
        if done:  # the final map (smoothed layers included) once, so that its snapshot has it
            try:
                self.strategy.focus_map()
            except STRATEGY_ERRORS as error:
                # The measurement is stored: its reply must say so. The map is asked for
                # again when read, and fails there, where the failure belongs.
                log.error("slide %s: its final map failed: %r", self.id, error)
        if done or len(self.history) - self.n_snapshot >= self.snapshot_every:
            self.save_snapshot()
        return logged, True

    def _recorded(self, request: api.MeasurementIn, measurement: Measurement) -> Logged:
        logged = self.history[request.sequence]
        same_tile = (logged.acquisition.row, logged.acquisition.col) == (request.row, request.col)
        if not same_tile or logged.measurement != measurement:
            raise SlideConflictError(
                f"acquisition {request.sequence} was already recorded for tile "
                f"({logged.acquisition.row}, {logged.acquisition.col}) with "
                f"{json.dumps(measurement_record(logged.measurement))}; a different value "
                "cannot replace it"
            )
        return logged

    def focus_map(self) -> FocusMap:
        """A copy of the current maps (safe to read after the lock is released)."""
        return FocusMap(**dataclasses.asdict(self.strategy.focus_map()))  # asdict deep-copies

    def diagnose(self) -> SlideDiagnostics:
        """Counts, innovation statistics and the predicted risk of the scan so far."""
        return diagnose(self.history, self.strategy)


#: How far outside its stack a best focus may lie, um, at least: a stack's own reading
#: (a peak fitted past its last frame, a pair's or a single frame's estimate) reaches a
#: little beyond it, never this far; a height this far off is a unit gone wrong (nm, mm)
#: or another tile's, and one such value would move the next tiles' stacks with it.
MIN_REACH_OUTSIDE_UM = 50.0
#: ... or this many times the stack's span, for a wide stack.
REACH_OUTSIDE_SPANS = 4.0


def _check_within_reach(pending: Acquisition, measurement: Measurement) -> None:
    """SlideError (422) for a best focus far outside the stack it was read from (a laser
    reading has no stack: its height is the sensor's)."""
    z_um = measurement.z_um
    if z_um is None or pending.purpose is Purpose.LASER:
        return
    low_um, high_um = pending.z.low_um, pending.z.high_um
    reach_um = max(MIN_REACH_OUTSIDE_UM, REACH_OUTSIDE_SPANS * (high_um - low_um))
    if not low_um - reach_um <= z_um <= high_um + reach_um:
        raise SlideError(
            f"z_um {z_um:g} lies {max(low_um - z_um, z_um - high_um):g} um outside the stack "
            f"of acquisition {pending.index} ({low_um:g} to {high_um:g} um), beyond the "
            f"{reach_um:g} um a stack's reading can reach: a unit gone wrong (nm or mm for "
            "um), or another tile's height?",
            ("body", "z_um"),
        )
