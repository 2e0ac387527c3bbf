"""The live slides: every slide of the store, those in use kept in memory within the budget.

`Slides` creates slides, rebuilds one from its store on first use after a restart
or an eviction (`slide.Slide.load`), and drops the least recently used idle ones
when the live slides exceed the budget's count or bytes.

Concurrency: every operation on a slide runs under that slide's asyncio lock,
in a worker thread (strategy work and the store's commit stay off the event
loop), so requests on one slide are serialised and different slides proceed
side by side. Several estimators may share one store (replicas on PostgreSQL): a
cached slide is checked against the store's event count before each request
(`Slides._current`) and rebuilt from its snapshot and log if another writer moved it
on; an append that loses the race for a sequence (the store's SequenceConflictError)
rebuilds the slide the same way and does the request again on the log's state.
A slide restored from a snapshot whose state then fails under a request (an error
that is neither the domain's refusal nor the store's) is rebuilt from its log alone,
its snapshot replaced, and the request done again on it.

The strategies (`slide`, and through it every strategy module) are not imported
with this module, but by `load_strategies`: in the background once the service
serves (`app`), or by the first slide that needs them. They took most of the
service's start-up time.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

from focustrack_client import models as api
from focustrack_estimator.budget import Budget, GridLimits
from focustrack_estimator.errors import (
    STRATEGY_ERRORS,
    SlideConflictError,
    SlideError,
    SlideNotFoundError,
)
from focustrack_estimator.event_store import (
    EventStore,
    SequenceConflictError,
    SlideRecord,
    StoreError,
)
from focustrack_estimator.memory import release_memory
from focustrack_estimator.prior import BODY_LOC, decode_prior, takes_prior, with_prior
from focustrack_estimator.records import config_of

if TYPE_CHECKING:
    from focustrack_client.models import StrategyInfo
    from focustrack_estimator.registry import Catalogue
    from focustrack_estimator.slide import Slide

T = TypeVar("T")

log = logging.getLogger(__name__)

_LOADING = threading.Lock()
_loaded = threading.Event()


def load_strategies() -> type[Slide]:
    """The `Slide` class, every strategy imported with it on the first call.

    What that import loads lives as long as the process: it goes out of the
    collector's sight (`gc.freeze`, as the app's start does with what it
    loaded), before any slide exists, so that no slide is frozen with it.
    """
    with _LOADING:
        from focustrack_estimator.slide import Slide

        if not _loaded.is_set():
            gc.collect()
            gc.freeze()
            _loaded.set()
    return Slide


def strategies_loaded() -> bool:
    """Whether `load_strategies` has imported the strategies (the first slide waits for them
    otherwise)."""
    return _loaded.is_set()


class _RestoredStateError(Exception):
    """A slide restored from a snapshot failed under a request (`error`): its log decides."""

    def __init__(self, error: Exception) -> None:
        super().__init__(str(error))
        self.error = error


class Slides:
    """Every slide of the store; live ones cached in memory (least recently used evicted
    beyond the budget), others rebuilt on first use. `catalogue`: the strategies served
    (None: the estimator's own); `discarded` is called for each snapshot found wanting."""

    def __init__(
        self,
        store: EventStore,
        *,
        limits: GridLimits,
        budget: Budget,
        snapshot_every: int,
        timer: Callable[[float], None] = lambda _: None,
        catalogue: Catalogue | None = None,
        discarded: Callable[[], None] = lambda: None,
    ) -> None:
        self.store = store
        self._discarded = discarded
        self.limits = limits
        self.budget = budget
        self.snapshot_every = snapshot_every
        self._timer = timer
        self._catalogue = catalogue
        self._live: OrderedDict[str, Slide] = OrderedDict()  # least recently used first
        self._locks: dict[str, asyncio.Lock] = {}

    @property
    def n_live(self) -> int:
        return len(self._live)

    def catalogue(self) -> Catalogue:
        """The strategies served (their modules imported on the first call)."""
        load_strategies()
        from focustrack_estimator.slide_strategy import served

        return served(self._catalogue)

    def strategies(self) -> list[StrategyInfo]:
        """Every strategy served with its parameters' schema and defaults, by name."""
        from focustrack_estimator.params import strategy_infos

        return strategy_infos(self.catalogue())

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
        while len(self._live) > 1 and self.budget.over(len(self._live), self.live_bytes):
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
        """Check the configuration (grid, budget, parameters) by building its strategy, store
        it, and return the new id."""
        slide_id = uuid.uuid4().hex
        slide = await asyncio.to_thread(self._new, slide_id, config)
        self._keep(slide)
        await self._evict()
        return slide_id

    def _new(self, slide_id: str, config: api.SlideCreate) -> Slide:
        slide = self._checked(slide_id, config)
        self.store.create_slide(slide_id, slide.config.model_dump(mode="json"))
        return slide

    def _checked(self, slide_id: str, config: api.SlideCreate) -> Slide:
        """Slide `slide_id` of `config`, checked against this service's limits, not stored."""
        return load_strategies().checked(
            slide_id,
            config,
            self.store,
            limits=self.limits,
            budget=self.budget,
            snapshot_every=self.snapshot_every,
            timer=self._timer,
            catalogue=self._catalogue,
        )

    async def record(self, slide_id: str) -> SlideRecord:
        """The slide's stored configuration and progress; SlideNotFoundError if none."""
        record = await asyncio.to_thread(self.store.slide, slide_id)
        if record is None:
            raise SlideNotFoundError(f"no slide {slide_id!r}")
        return record

    async def page(self, after: tuple[float, str] | None, limit: int) -> list[SlideRecord]:
        """At most `limit` slides' stored configuration and progress, oldest first, after
        the slide created at `after` (created_s, id) only when given."""
        return await asyncio.to_thread(self.store.slides_after, after, limit)

    async def count(self) -> int:
        """How many slides the store holds."""
        return await asyncio.to_thread(self.store.count_slides)

    async def run(self, slide_id: str, work: Callable[[Slide], T]) -> T:
        """`work(slide)` under the slide's lock, in a worker thread; rebuilds the slide if needed.

        If the work fails past the domain's checks, the live slide may be half-updated
        (strategy advanced, commit failed): it is dropped, to be rebuilt from its log.
        """
        async with self._lock(slide_id):
            try:
                try:
                    result = await self._attempt(slide_id, work, use_snapshot=True)
                except SequenceConflictError:
                    # Another replica logged first: this state is behind the log. Take the
                    # log's and do the work again on it (a measurement it already holds is
                    # answered as recorded, or refused if it differs): one history, no fork.
                    self._live.pop(slide_id, None)
                    result = await self._attempt(slide_id, work, use_snapshot=True)
                except _RestoredStateError as failed:
                    log.warning(
                        "slide %s: its state restored from a snapshot failed (%r); "
                        "rebuilding it from its log",
                        slide_id, failed.error,
                    )  # fmt: skip
                    self._discarded()
                    result = await self._attempt(slide_id, work, use_snapshot=False)
            except SlideNotFoundError:
                self._live.pop(slide_id, None)  # deleted through another estimator
                self._locks.pop(slide_id, None)  # keep no lock for ids that do not exist
                raise
            except SlideError:
                raise
            except Exception as error:
                self._live.pop(slide_id, None)
                if isinstance(error, SequenceConflictError):
                    raise SlideConflictError(
                        f"slide {slide_id}'s log is at acquisition {error.current}: it was "
                        "recorded elsewhere; ask for the next acquisition again"
                    ) from None
                if isinstance(error, STRATEGY_ERRORS):
                    raise SlideError(f"strategy failed on slide {slide_id}: {error}") from None
                raise
        await self._evict()
        return result

    async def _attempt(self, slide_id: str, work: Callable[[Slide], T], *, use_snapshot: bool) -> T:
        """`work(slide)` on the live slide, loaded first if need be (`use_snapshot`: from its
        snapshot if it has one that checks out, else from its log alone)."""
        slide = self._live.get(slide_id)
        if slide is None or not await asyncio.to_thread(self._current, slide):
            slide = await asyncio.to_thread(self._load, slide_id, use_snapshot)
        self._keep(slide)
        try:
            return await asyncio.to_thread(work, slide)
        except (SlideError, StoreError):
            raise
        except Exception as error:
            if not slide.restored:
                raise
            self._live.pop(slide_id, None)
            raise _RestoredStateError(error) from error

    def _current(self, slide: Slide) -> bool:
        """Whether the cached `slide` is what the store holds (another estimator on the same
        store may have logged events, or set a prior before the first); SlideNotFoundError
        if the slide was deleted there. One indexed read of the event count; the
        configuration is compared only while the log is empty (the only time it changes)."""
        n_events = self.store.n_events(slide.id)
        if n_events is None:
            raise SlideNotFoundError(f"no slide {slide.id!r}")
        if n_events != len(slide.history):
            return False
        if n_events:
            return True
        record = self.store.slide(slide.id)
        return record is not None and record.config == slide.config.model_dump(mode="json")

    def _load(self, slide_id: str, use_snapshot: bool) -> Slide:
        record = self.store.slide(slide_id)
        if record is None:
            raise SlideNotFoundError(f"no slide {slide_id!r}")
        return load_strategies().load(
            record,
            self.store,
            snapshot_every=self.snapshot_every,
            timer=self._timer,
            catalogue=self._catalogue,
            use_snapshot=use_snapshot,
            discarded=self._discarded,
        )

    async def set_prior(self, slide_id: str, npy: bytes) -> None:
        """Make the .npy file `npy` the prior map of a slide not yet scanned (`prior`):
        SlideNotFoundError, SlideConflictError once an acquisition is recorded, SlideError
        for a strategy without a prior map or a map that does not fit the slide."""
        async with self._lock(slide_id):
            try:
                slide = await asyncio.to_thread(self._with_prior, slide_id, npy)
            except SlideNotFoundError:
                self._locks.pop(slide_id, None)  # keep no lock for ids that do not exist
                raise
            except SequenceConflictError as error:  # another service on the store measured
                raise _not_before_the_first(slide_id, error.current) from None
            self._keep(slide)
        await self._evict()

    def _with_prior(self, slide_id: str, npy: bytes) -> Slide:
        record = self.store.slide(slide_id)
        if record is None:
            raise SlideNotFoundError(f"no slide {slide_id!r}")
        if record.n_events:
            raise _not_before_the_first(slide_id, record.n_events)
        config = config_of(record)
        takes = [name for name, entry in self.catalogue().strategies.items() if takes_prior(entry)]
        if config.strategy not in takes:
            raise SlideError(
                f"slide {slide_id} is scanned with {config.strategy!r}, which takes no prior "
                f"map; {', '.join(takes) or 'no strategy served'} does",
                BODY_LOC,
            )
        prior = decode_prior(npy, config.grid.rows, config.grid.cols)
        slide = self._checked(slide_id, with_prior(config, prior))
        # the store's SequenceConflictError if an event was logged since the check above
        self.store.replace_config(slide_id, slide.config.model_dump(mode="json"))
        return slide

    def save_snapshots(self) -> None:
        """Snapshot every live slide that has events since its last snapshot (at shutdown),
        until the store fails: each slide would wait out the store's timeout in turn (5 s
        each on PostgreSQL, minutes for a hundred slides), and the logs hold every event."""
        slides = list(self._live.values())
        for done, slide in enumerate(slides):
            if not slide.save_snapshot():
                log.warning(
                    "the store failed: %d slides' snapshots not stored (each is rebuilt from "
                    "its log when next asked for)",
                    len(slides) - done,
                )
                return

    async def delete(self, slide_id: str) -> None:
        async with self._lock(slide_id):
            if not await asyncio.to_thread(self.store.delete_slide, slide_id):
                raise SlideNotFoundError(f"no slide {slide_id!r}")
            if self._live.pop(slide_id, None) is not None:
                await asyncio.to_thread(release_memory)
        self._locks.pop(slide_id, None)


def _not_before_the_first(slide_id: str, n_events: int) -> SlideConflictError:
    return SlideConflictError(
        f"slide {slide_id} has {n_events} acquisitions recorded: its prior map can only be "
        "set before the first (create a new slide to scan with another)"
    )
