"""The estimator's domain: live slides, each a strategy rebuilt from its durable log.

A `Slide` pairs a strategy with the history of what it was asked and told;
`Slides` keeps the live ones in memory, creates new ones, and rebuilds a slide
from its store on first use after a restart: from its newest snapshot (the
strategy's state, written every `snapshot_every` measurements, when the scan
completes and at shutdown) and the events logged after it, or from the whole
log when there is no snapshot that fits. Strategies are deterministic, so the
replay gives back the same state; it checks that every acquisition and outcome
comes out as logged, and tolerates differences of floating-point noise (another
numpy or BLAS) with a warning. The log stays the source of truth.

Concurrency: every operation on a slide runs under that slide's asyncio lock,
in a worker thread (strategy work and the SQLite commit stay off the event
loop), so requests on one slide are serialised and different slides proceed
side by side. A measurement is committed before its outcome is returned.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import dataclasses
import gc
import logging
import math
import sqlite3
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar, overload

import numpy as np

from focustrack_client import models as api
from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    ZRange,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import map_layers
from focustrack_core.rest import to_domain
from focustrack_estimator import registry
from focustrack_estimator.diagnostics import InnovationDiagnostics, innovation_diagnostics
from focustrack_estimator.errors import (
    ReplayMismatchError,
    SlideConflictError,
    SlideError,
    SlideNotFoundError,
)
from focustrack_estimator.heatmap import MAGMA, VIRIDIS, heat_map_png
from focustrack_estimator.params import resolve_params
from focustrack_estimator.snapshot import SnapshotError, encode, restore
from focustrack_estimator.store import Event, Store
from focustrack_estimator.strategy import Cost, Strategy, StrategyParams

log = logging.getLogger(__name__)

#: Exceptions a strategy may raise on absurd parameters or input (turned into a 422).
STRATEGY_ERRORS = (ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError)

T = TypeVar("T")


def acquisition_record(acquisition: Acquisition) -> dict[str, Any]:
    return dataclasses.asdict(acquisition)


def measurement_record(measurement: Measurement) -> dict[str, Any]:
    return {
        "z_um": measurement.z_um,
        "sigma_um": measurement.sigma_um,
        "flags": sorted(measurement.flags),
    }


def measurement_of(record: dict[str, Any]) -> Measurement:
    return Measurement(
        record["z_um"], record["sigma_um"], frozenset(FocusFlag(f) for f in record["flags"])
    )


def outcome_record(outcome: Outcome) -> dict[str, Any]:
    record = dataclasses.asdict(outcome)
    # as logged before tiles kept several frames: the logs of those scans still replay
    planes_um = record.pop("planes_um")
    return {**record, "planes_um": list(planes_um)} if planes_um else record


def acquisition_of(record: dict[str, Any]) -> Acquisition:
    return Acquisition(
        **{**record, "z": ZRange(**record["z"]), "purpose": Purpose(record["purpose"])}
    )


def outcome_of(record: dict[str, Any]) -> Outcome:
    return Outcome(**{**record, "planes_um": tuple(record.get("planes_um", ()))})


#: Replayed and logged numbers that differ by at most this (relative, and absolute in um)
#: are the same result computed with other round-off (another numpy, BLAS or CPU).
REPLAY_TOLERANCE = 1e-6


def same_up_to_round_off(replayed: Any, logged: Any) -> bool:
    """Whether two records (JSON-like) are equal except for floats within `REPLAY_TOLERANCE`.

    Integers, flags, strings and None must match exactly: a tile, a frame count or
    an acceptance that changed is a different outcome, not round-off.
    """
    if isinstance(replayed, dict) and isinstance(logged, dict):
        return replayed.keys() == logged.keys() and all(
            same_up_to_round_off(replayed[k], logged[k]) for k in replayed
        )
    if isinstance(replayed, float) and isinstance(logged, float):
        return math.isclose(replayed, logged, rel_tol=REPLAY_TOLERANCE, abs_tol=REPLAY_TOLERANCE)
    return type(replayed) is type(logged) and replayed == logged


@dataclasses.dataclass(frozen=True)
class Logged:
    """One recorded acquisition, in memory: the tile asked for, what was sent, what it did."""

    acquisition: Acquisition
    measurement: Measurement
    outcome: Outcome


class History(Sequence[Logged]):
    """A slide's logged acquisitions in order; those a snapshot covers are read on first use.

    After a restart the strategy comes from its snapshot, and only the events
    after it are needed (to replay): reading and decoding the events the
    snapshot covers took seconds for a 200x200 slide (40 000 events), so they
    are read from the store when something first asks for them (diagnostics,
    the re-post of an old measurement). `load` returns them.
    """

    def __init__(self, load: Callable[[], list[Logged]] | None = None, n_unread: int = 0) -> None:
        self._load, self._n_unread = load, n_unread
        self._items: list[Logged] = []

    def _read(self) -> None:
        if self._load is not None:
            self._items[:0] = self._load()
            self._load, self._n_unread = None, 0

    def __len__(self) -> int:
        return self._n_unread + len(self._items)

    @overload
    def __getitem__(self, index: int) -> Logged: ...

    @overload
    def __getitem__(self, index: slice) -> list[Logged]: ...

    def __getitem__(self, index: int | slice) -> Logged | list[Logged]:
        if isinstance(index, slice):
            self._read()
            return self._items[index]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"history index {index} out of range")
        if index < self._n_unread:
            self._read()
        return self._items[index - self._n_unread]

    def __iter__(self) -> Iterator[Logged]:
        self._read()
        return iter(self._items)

    def append(self, logged: Logged) -> None:
        self._items.append(logged)


class Slide:
    """One slide's live strategy and its history. Not thread-safe: `Slides` serialises calls.

    `timer` is called with the seconds spent in each strategy call (for /metrics).
    A snapshot of the strategy is stored every `snapshot_every` measurements
    and when the scan completes.
    """

    def __init__(
        self,
        slide_id: str,
        config: api.SlideCreate,
        params: StrategyParams,
        store: Store,
        timer: Callable[[float], None] = lambda _: None,
        snapshot_every: int = 200,
        catalogue: registry.Catalogue = registry.SERVED,
    ) -> None:
        self.id = slide_id
        self.config = config
        self.store = store
        self._timer = timer
        self.snapshot_every = snapshot_every
        self.history = History()
        self.n_snapshot = 0  # events covered by the newest snapshot stored
        self._snapshots = True  # False once the strategy's state proved impossible to store
        try:
            self.cost = cost_of(config, params, catalogue)  # its share of the live slides' budget
            self.strategy: Strategy = catalogue.create(
                config.strategy, to_domain.slide_settings(config), params
            )
            self.next()  # plan the first acquisition: absurd parameters fail here, at creation
        except SlideError:
            raise
        except STRATEGY_ERRORS as error:
            raise SlideError(
                f"strategy {config.strategy!r} rejected its settings or parameters: {error}",
                ("body",),
            ) from None

    @property
    def grid(self) -> ScanGrid:
        return self.strategy.grid

    def next(self) -> Acquisition | None:
        start_s = time.perf_counter()
        acquisition = self.strategy.next_acquisition()
        self._timer(time.perf_counter() - start_s)
        return acquisition

    def replay(self, events: list[Event]) -> None:
        """Rebuild the state from the logged events, checking each comes out as logged.

        A replayed acquisition or outcome that differs from the logged one by
        round-off only (`same_up_to_round_off`) is logged as a warning and the
        replay goes on; the history keeps the logged records, which the
        clients were given. Any other difference is a ReplayMismatchError.
        """
        for event in events:
            acquisition = self.strategy.next_acquisition()
            replayed = None if acquisition is None else acquisition_record(acquisition)
            self._check(event, "acquisition", replayed, event.acquisition)
            assert acquisition is not None  # checked against the logged one
            measurement = measurement_of(event.measurement)
            outcome = self.strategy.record(acquisition, measurement)
            self._check(event, "outcome", outcome_record(outcome), event.outcome)
            self.history.append(
                Logged(acquisition_of(event.acquisition), measurement, outcome_of(event.outcome))
            )

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

    def cover_history(self, n_events: int) -> None:
        """Take the first `n_events` logged events as the history without replaying them (a
        snapshot covers them); they are read from the store when first needed (`History`)."""

        def load() -> list[Logged]:
            return [
                Logged(
                    acquisition_of(e.acquisition),
                    measurement_of(e.measurement),
                    outcome_of(e.outcome),
                )
                for e in self.store.events(self.id)[:n_events]
            ]

        self.history = History(load, n_events)

    def save_snapshot(self) -> None:
        """Store the strategy's state as the snapshot after the history's events.

        Never fails the request: a state that cannot be encoded turns snapshots
        off for this slide (it is then rebuilt from its whole log), a store error
        leaves the older snapshot (the log has every event either way).
        """
        if not self._snapshots or len(self.history) <= self.n_snapshot:
            return
        try:
            blob = encode(self.strategy)
            self.store.put_snapshot(self.id, len(self.history), blob)
        except SnapshotError as error:
            self._snapshots = False
            log.warning("slide %s: no snapshots for its strategy: %s", self.id, error)
            return
        except sqlite3.Error as error:
            log.warning("slide %s: snapshot not stored: %s", self.id, error)
            return
        self.n_snapshot = len(self.history)

    def measure(self, request: api.MeasurementIn) -> tuple[Logged, bool]:
        """Record a measurement (durably) or return the one already recorded for it.

        Returns the logged acquisition with its outcome, and whether it is new
        (False: an idempotent re-post).
        Raises SlideError (tile outside the grid), SlideConflictError (not the pending
        acquisition, a re-post with another value, the scan is complete).
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
        start_s = time.perf_counter()
        outcome = self.strategy.record(pending, measurement)
        done = self.strategy.next_acquisition() is None
        self._timer(time.perf_counter() - start_s)
        event = Event(
            pending.index,
            acquisition_record(pending),
            measurement_record(measurement),
            outcome_record(outcome),
        )
        self.store.append(self.id, event, accepted=outcome.accepted, done=done)
        logged = Logged(pending, measurement, outcome)
        self.history.append(logged)
        if done:  # the final map (smoothed layers included) once, so that its snapshot has it
            self.strategy.focus_map()
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
                f"{measurement_record(logged.measurement)}; a different value cannot replace it"
            )
        return logged

    def focus_map(self) -> FocusMap:
        """A copy of the current maps (safe to read after the lock is released)."""
        return FocusMap(**dataclasses.asdict(self.strategy.focus_map()))  # asdict deep-copies


@dataclasses.dataclass(frozen=True)
class GridLimits:
    """The largest grid a slide may have: tiles per side and in all (a service setting).

    Memory grows with the grid: kf-2d keeps (3 + 2 cols)^2 floats per member
    model (145 MB for 18 members at 500 columns), every strategy a few maps of
    rows x cols floats and the history a record per acquisition.
    """

    max_side: int = 500
    max_tiles: int = 250_000

    def check(self, grid: api.Grid) -> None:
        """Raise a SlideError (422) naming the limit if `grid` exceeds it."""
        if max(grid.rows, grid.cols) > self.max_side or grid.rows * grid.cols > self.max_tiles:
            raise SlideError(
                f"grid {grid.rows}x{grid.cols} ({grid.rows * grid.cols} tiles) exceeds this "
                f"service's limit of {self.max_side} tiles per side and {self.max_tiles} tiles "
                "(settings --max-grid-side, --max-grid-tiles)",
                ("body", "grid"),
            )


#: Tiles per side of the trial scan of `probe` (fewer where the slide has fewer).
PROBE_SIDE = 4


def probe(
    config: api.SlideCreate,
    params: StrategyParams,
    catalogue: registry.Catalogue = registry.SERVED,
) -> None:
    """Scan a small grid (at most `PROBE_SIDE` a side) with the slide's strategy, settings and
    parameters, with the sharpest measurements the API allows, jumping up and down, then
    make its map; a SlideError (422) if the strategy fails on the way.

    Bounds on each value cannot see every combination that breaks the arithmetic (a
    slope sigma of 1e30 with a 1 nm measurement made P singular): a slide whose
    strategy fails this probe would fail on a real scan too and stay stuck there.
    """
    grid = config.grid.model_copy(
        update={
            "rows": min(config.grid.rows, PROBE_SIDE),
            "cols": min(config.grid.cols, PROBE_SIDE),
        }
    )
    settings = to_domain.slide_settings(config.model_copy(update={"grid": grid}))
    try:
        strategy = catalogue.create(config.strategy, settings, params)
    except STRATEGY_ERRORS:
        return  # a strategy that needs a larger grid (a survey): the slide's own was built
    try:
        while (acquisition := strategy.next_acquisition()) is not None:
            jump_um = 10.0 * config.dof_um * (-1) ** acquisition.index
            measurement = Measurement(acquisition.z.center_um + jump_um, api.MIN_SIGMA_UM)
            strategy.record(acquisition, measurement)
        strategy.focus_map()
    except STRATEGY_ERRORS as error:
        raise SlideError(
            f"strategy {config.strategy!r} with these settings and parameters fails on a "
            f"{grid.rows}x{grid.cols} trial scan ({type(error).__name__}: {error}): "
            "they are not usable (non-physical values?)",
            ("body",),
        ) from None


def cost_of(
    config: api.SlideCreate,
    params: StrategyParams,
    catalogue: registry.Catalogue = registry.SERVED,
) -> Cost:
    """The projected cost of a slide (its strategy's cost model, with its parameters)."""
    return catalogue.cost(config.strategy, to_domain.slide_settings(config), params)


@dataclasses.dataclass(frozen=True)
class Budget:
    """What one slide may cost, and what the live slides together may hold (service settings).

    A slide is refused at creation (422) when its strategy's projected peak memory
    or compute per tile exceeds `max_slide_bytes` or `max_tile_s`. The defaults
    admit kf-2d on a 200x200 grid (about 220 MiB, 2.5 ms per tile). Live slides are
    evicted, least recently used first, when there are more than `max_live_slides`
    or their projected bytes add up to more than `max_live_bytes`; an evicted slide
    is rebuilt from its snapshot and log on its next request.
    """

    max_slide_bytes: int = 512 * 2**20
    max_tile_s: float = 0.1
    max_live_slides: int = 100
    max_live_bytes: int = 768 * 2**20

    def __post_init__(self) -> None:
        counts = (self.max_slide_bytes, self.max_live_slides, self.max_live_bytes)
        if min(counts) < 1 or not self.max_tile_s > 0:
            raise ValueError(f"the budget's limits must be positive, got {self}")

    def check(
        self,
        config: api.SlideCreate,
        params: StrategyParams,
        catalogue: registry.Catalogue = registry.SERVED,
    ) -> Cost:
        """The slide's projected cost; a SlideError (422) saying which limit it exceeds."""
        cost = cost_of(config, params, catalogue)
        where = f"strategy {config.strategy!r} on a {config.grid.rows}x{config.grid.cols} grid"
        if cost.peak_bytes > self.max_slide_bytes:
            raise SlideError(
                f"{where} with these parameters is projected to need {cost.peak_bytes / 2**20:.0f} "
                f"MiB; this service allows {self.max_slide_bytes / 2**20:.0f} MiB per slide "
                "(setting --max-slide-bytes): use a smaller grid or bank",
                ("body",),
            )
        if cost.seconds_per_tile > self.max_tile_s:
            raise SlideError(
                f"{where} with these parameters is projected to need {cost.seconds_per_tile:.3g} s "
                f"of computation per tile; this service allows {self.max_tile_s:g} s "
                "(setting --max-tile-seconds): use a smaller grid or bank",
                ("body",),
            )
        return cost


def release_memory() -> None:
    """Give freed memory back to the system: collect cycles, then trim glibc's heap.

    Without the trim, a dropped slide's arrays below glibc's (self-raising) mmap
    threshold stay in the process's heap, and its resident memory never shrinks.
    """
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _glibc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return libc if libc is not None and hasattr(libc, "malloc_trim") else None


_LIBC = _glibc()


class Slides:
    """Every slide of the store; live ones cached in memory (least recently used evicted
    beyond the budget), others rebuilt on first use."""

    def __init__(
        self,
        store: Store,
        timer: Callable[[float], None] = lambda _: None,
        *,
        snapshot_every: int = 200,
        limits: GridLimits = GridLimits(),
        budget: Budget = Budget(),
        catalogue: registry.Catalogue = registry.SERVED,
    ) -> None:
        if snapshot_every < 1:
            raise ValueError(f"snapshot_every must be at least 1, got {snapshot_every}")
        self.store = store
        self._timer = timer
        self.snapshot_every = snapshot_every
        self.limits = limits
        self.budget = budget
        self.catalogue = catalogue
        self._live: OrderedDict[str, Slide] = OrderedDict()  # least recently used first
        self._locks: dict[str, asyncio.Lock] = {}

    @property
    def n_live(self) -> int:
        return len(self._live)

    @property
    def live_bytes(self) -> int:
        """The projected peak bytes of the live slides together."""
        return sum(slide.cost.peak_bytes for slide in self._live.values())

    def _keep(self, slide: Slide) -> None:
        self._live[slide.id] = slide
        self._live.move_to_end(slide.id)

    async def _evict(self) -> None:
        """Drop least recently used idle slides until the live ones fit the budget.

        Each is snapshotted first (its next request restores the snapshot instead
        of replaying its log); slides with a request under way are left alone.
        """
        evicted = False
        while len(self._live) > 1 and (
            len(self._live) > self.budget.max_live_slides
            or self.live_bytes > self.budget.max_live_bytes
        ):
            newest = next(reversed(self._live))  # the slide just used stays
            idle = [i for i in self._live if i != newest and not self._lock(i).locked()]
            if not idle:
                break
            slide_id = idle[0]
            async with self._lock(slide_id):
                slide = self._live.pop(slide_id, None)
                if slide is not None:
                    await asyncio.to_thread(slide.save_snapshot)
                    evicted = True
            del slide
        if evicted:
            await asyncio.to_thread(release_memory)

    def _lock(self, slide_id: str) -> asyncio.Lock:
        return self._locks.setdefault(slide_id, asyncio.Lock())

    async def create(self, config: api.SlideCreate) -> str:
        """Check the configuration (grid, budget) by building its strategy, store it, and
        return the new id."""
        self.limits.check(config.grid)
        params = resolve_params(config.strategy, config.params, self.catalogue)
        self.budget.check(config, params, self.catalogue)
        # Stored and served with every parameter resolved, as JSON (a tuple is a list there).
        config = config.model_copy(update={"params": params.model_dump(mode="json")})
        slide_id = uuid.uuid4().hex
        slide = await asyncio.to_thread(
            Slide, slide_id, config, params, self.store, self._timer, self.snapshot_every,
            self.catalogue,
        )  # fmt: skip
        await asyncio.to_thread(probe, config, params, self.catalogue)
        await asyncio.to_thread(self.store.create_slide, slide_id, config.model_dump(mode="json"))
        self._keep(slide)
        await self._evict()
        return slide_id

    async def run(self, slide_id: str, work: Callable[[Slide], T]) -> T:
        """`work(slide)` under the slide's lock, in a worker thread; rebuilds the slide if needed.

        If the work fails past the domain's checks, the live slide may be half-updated
        (strategy advanced, commit failed): it is dropped, to be rebuilt from its log.
        """
        async with self._lock(slide_id):
            slide = self._live.get(slide_id)
            try:
                if slide is None:
                    slide = await asyncio.to_thread(self._load, slide_id)
                self._keep(slide)
                result = await asyncio.to_thread(work, slide)
            except SlideNotFoundError:
                self._locks.pop(slide_id, None)  # keep no lock for ids that do not exist
                raise
            except SlideError:
                raise
            except Exception as error:
                self._live.pop(slide_id, None)
                if isinstance(error, STRATEGY_ERRORS):
                    raise SlideError(f"strategy failed on slide {slide_id}: {error}") from None
                raise
        await self._evict()
        return result

    def _load(self, slide_id: str) -> Slide:
        record = self.store.slide(slide_id)
        if record is None:
            raise SlideNotFoundError(f"no slide {slide_id!r}")
        config = api.SlideCreate.model_validate(record.config)
        params = resolve_params(config.strategy, config.params, self.catalogue)
        slide = Slide(
            slide_id, config, params, self.store, self._timer, self.snapshot_every, self.catalogue
        )
        snapshot = self.store.snapshot(slide_id)
        if snapshot is not None and snapshot[0] <= record.n_events:
            try:
                restore(slide.strategy, snapshot[1])
                slide.cover_history(snapshot[0])
                slide.n_snapshot = snapshot[0]
            except SnapshotError as error:
                log.warning("slide %s: snapshot not used, replaying its log: %s", slide_id, error)
                slide = Slide(
                    slide_id, config, params, self.store, self._timer, self.snapshot_every,
                    self.catalogue,
                )  # fmt: skip
        # Only the events after the snapshot are read now (the others when first needed).
        slide.replay(self.store.events(slide_id, start=len(slide.history)))
        return slide

    def save_snapshots(self) -> None:
        """Snapshot every live slide that has events since its last snapshot (at shutdown)."""
        for slide in list(self._live.values()):
            slide.save_snapshot()

    async def delete(self, slide_id: str) -> None:
        async with self._lock(slide_id):
            if not await asyncio.to_thread(self.store.delete_slide, slide_id):
                raise SlideNotFoundError(f"no slide {slide_id!r}")
            if self._live.pop(slide_id, None) is not None:
                await asyncio.to_thread(release_memory)
        self._locks.pop(slide_id, None)


# --- Diagnostics and map export: pure functions of a slide's history and maps. ---

#: Innovation lags the whiteness test pools (fewer when the scan is short).
MAX_LAG = 20


@dataclasses.dataclass(frozen=True)
class SlideDiagnostics:
    """Counts over a slide's acquisitions and, when there are enough, its innovation statistics."""

    n_acquisitions: int
    n_measured: int  # acquisitions that asked for a best focus
    n_accepted: int  # measurements used as observations
    n_rejected: int  # measured, but not an observation: edge, flat, gated out
    innovations: InnovationDiagnostics | None
    innovations_note: str | None  # why `innovations` is None


def diagnose(history: Sequence[Logged]) -> SlideDiagnostics:
    """Diagnostics from the accepted outcomes' innovations and NIS (S = innovation^2 / NIS).

    Gated-out measurements are counted as rejected but left out of the innovation
    statistics, which describe the filter's consistency on what it used.
    """
    n_measured = sum(logged.acquisition.measure for logged in history)
    n_accepted = sum(logged.outcome.accepted for logged in history)
    innovation_um, variance_um2 = [], []
    for logged in history:
        outcome = logged.outcome
        if not outcome.accepted or outcome.innovation_um is None or outcome.nis is None:
            continue
        innovation_um.append(outcome.innovation_um)
        # NIS = 0 only for a zero innovation, whose normalised value is 0 whatever S is.
        variance_um2.append(outcome.innovation_um**2 / outcome.nis if outcome.nis > 0 else 1.0)
    innovations, note = None, None
    n = len(innovation_um)
    if n < 3:
        note = f"{n} innovation(s) logged; at least 3 are needed"
    else:
        try:
            innovations = innovation_diagnostics(
                np.array(innovation_um), np.array(variance_um2), max_lag=min(MAX_LAG, n - 2)
            )
        except ValueError as error:  # a constant sequence has no autocorrelation
            note = str(error)
    return SlideDiagnostics(
        len(history), n_measured, n_accepted, n_measured - n_accepted, innovations, note
    )


def map_png(focus_map: FocusMap, title: str) -> bytes:
    """A PNG heat map of the posterior focus map and its sigma, side by side (`heatmap`)."""
    layers = map_layers(focus_map)
    return heat_map_png(
        [
            ("posterior_um", layers["posterior_um"], VIRIDIS),
            ("posterior_sigma_um", layers["posterior_sigma_um"], MAGMA),
        ],
        title,
    )
