"""Where the estimator keeps its slides: the `EventStore` interface and what goes through it.

Event sourcing: a slide is its configuration plus the ordered log of
(sequence, acquisition, measurement, outcome) events; strategies are
deterministic, so replaying the log rebuilds the live state. The log is the
source of truth; beside it a store keeps each slide's newest snapshot (an
opaque blob of the strategy's state after its first n events), so that a
restart replays only the events after it. A store knows nothing of
strategies: configurations and events are JSON objects, snapshots bytes.
A snapshot is stored with its checksum (`snapshot_digest`) and given back only
if it matches: what a snapshot holds is checked again by its reader
(`slide.Slide.load`), which falls back to the log.

Appends are optimistic: each names the sequence it expects to write (the
slide's event count as its writer last saw it), and a log that has moved on
since (another writer appended first) refuses it with `SequenceConflictError`,
which tells the writer to reload the slide. SQLite (`sqlite_store`) is the
embedded implementation, PostgreSQL (`postgres_store`) the one that replicas share;
`open_store` opens one from a path or a URL.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, Protocol


class StoreError(Exception):
    """A request the store cannot honour (unknown slide, a slide that exists already), or
    a store it refuses to open (damaged, not a database, of a newer schema)."""


class SequenceConflictError(StoreError):
    """The slide's log is not where the append expected it: `current` events are logged
    (another writer moved it on, or the caller's sequence is wrong)."""

    def __init__(self, slide_id: str, expected: int, current: int) -> None:
        super().__init__(f"slide {slide_id!r} expects event {current}, got {expected}")
        self.slide_id, self.expected, self.current = slide_id, expected, current


class StoreUnavailableError(StoreError):
    """The database failed (I/O error, full disk, locked): what was asked may not be done."""


class StoreFullError(StoreUnavailableError):
    """The disk (or the store's file) is full: nothing of the write was kept; it may succeed
    once there is space again."""


class CorruptSnapshotError(StoreError):
    """A stored snapshot that is not what was written (its checksum does not match, or it was
    written before snapshots had one): not to be used; the slide's log is."""


class CorruptLogError(StoreError):
    """A slide's stored configuration or log record that fails its own checks (unreadable,
    of the wrong shape, out of its bounds): that slide cannot be served until it is repaired.
    `sequence` is the record's (None: the configuration)."""

    def __init__(self, slide_id: str, sequence: int | None, problem: str) -> None:
        where = "configuration" if sequence is None else f"log record {sequence}"
        super().__init__(f"slide {slide_id!r}: its stored {where} is corrupt: {problem}")
        self.slide_id, self.sequence = slide_id, sequence


@dataclass(frozen=True)
class SlideRecord:
    """A slide's stored configuration and progress (times are Unix seconds)."""

    id: str
    config: dict[str, Any]
    created_s: float
    updated_s: float
    n_events: int
    n_accepted: int
    done: bool


@dataclass(frozen=True)
class Event:
    """One logged acquisition with the measurement made for it and what it did."""

    sequence: int
    acquisition: dict[str, Any]
    measurement: dict[str, Any]
    outcome: dict[str, Any]


class Snapshot(NamedTuple):
    """A strategy's state after the slide's first `n_events` events (opaque bytes)."""

    n_events: int
    state: bytes


def snapshot_digest(slide_id: str, n_events: int, state: bytes) -> str:
    """The checksum a snapshot is stored with: SHA-256 (hex) of the slide's id, the number of
    events it stands for and its bytes, so that neither can be swapped for another's."""
    header = f"{slide_id}\0{n_events}\0".encode()
    return hashlib.sha256(header + state).hexdigest()


def checked_snapshot(slide_id: str, n_events: int, state: bytes, digest: str | None) -> Snapshot:
    """The snapshot read back with its stored checksum `digest`; CorruptSnapshotError if it
    has none (an older store's) or it does not match (`snapshot_digest`)."""
    if digest is None:
        raise CorruptSnapshotError(
            f"slide {slide_id!r}: its snapshot has no checksum (an older store's)"
        )
    if digest != snapshot_digest(slide_id, n_events, state):
        raise CorruptSnapshotError(
            f"slide {slide_id!r}: its snapshot (of {n_events} events) does not match its checksum"
        )
    return Snapshot(n_events, state)


class EventStore(Protocol):
    """Slides, their event logs and their newest snapshots, durable once a call returns.

    Every method may be called from several threads at once. Any of them may raise
    `StoreUnavailableError` when the database fails (`StoreFullError` when the disk is
    full), and the readers `CorruptLogError` for a record that does not decode.
    """

    @property
    def created(self) -> bool:
        """Whether the store was new (missing or empty) when it was opened."""
        ...

    @property
    def address(self) -> str:
        """Where the store is, fit for a log: a file's path, or a database's URL without
        its password."""
        ...

    def create_slide(self, slide_id: str, config: dict[str, Any]) -> SlideRecord:
        """A new slide with an empty log; StoreError if `slide_id` exists."""
        ...

    def slide(self, slide_id: str) -> SlideRecord | None:
        """The slide's record, or None if there is no such slide."""
        ...

    def n_events(self, slide_id: str) -> int | None:
        """How many events the slide's log holds, or None if there is no such slide: the
        cheap check of a slide cached in memory against what other writers logged."""
        ...

    def slides(self) -> list[SlideRecord]:
        """Every slide, oldest first."""
        ...

    def slides_after(self, after: tuple[float, str] | None, limit: int) -> list[SlideRecord]:
        """At most `limit` slides, oldest first (by creation time, then id), those after
        `after` (a slide's (created_s, id)) only when given: one page of the listing."""
        ...

    def count_slides(self) -> int: ...

    def replace_config(self, slide_id: str, config: dict[str, Any]) -> None:
        """Replace the configuration of a slide whose log is empty, and forget its snapshot
        (a state of the configuration replaced), atomically. SequenceConflictError if
        events are logged, StoreError if there is no such slide."""
        ...

    def delete_slide(self, slide_id: str) -> bool:
        """Forget a slide, its log and its snapshot; False if there was no such slide."""
        ...

    def append(self, slide_id: str, event: Event, *, accepted: bool, done: bool) -> None:
        """Log `event` as the slide's next one and update its progress, atomically.

        `event.sequence` is the sequence expected: the slide's event count (the log
        has no gaps). Raises SequenceConflictError (with the current count) if the
        log is elsewhere, StoreError if there is no such slide.
        """
        ...

    def events(self, slide_id: str, start: int = 0) -> list[Event]:
        """The slide's log in sequence order, from sequence `start` on."""
        ...

    def put_snapshot(self, slide_id: str, n_events: int, state: bytes) -> None:
        """Keep `state` as the slide's snapshot after its first `n_events` events (replacing
        an older one); a snapshot older than the one kept is ignored."""
        ...

    def snapshot(self, slide_id: str) -> Snapshot | None:
        """The slide's newest snapshot, or None; CorruptSnapshotError if it is not what was
        stored (`snapshot_digest`)."""
        ...

    def problem(self) -> str | None:
        """Why the store is degraded (its last write found the disk full, its checkpoints
        fail), or None while it is well."""
        ...

    def close(self) -> None:
        """Release the store (once; later calls do nothing)."""
        ...


#: The URL scheme of an SQLite store (``sqlite:///relative.db``, ``sqlite:////abs/path.db``).
SQLITE_SCHEME = "sqlite://"


def store_address(location: str) -> tuple[Literal["sqlite", "postgresql"], str]:
    """Which store `location` names, and its address: an SQLite file's path, a
    ``sqlite:///PATH`` URL (the path after the third slash, so ``sqlite:////data/e.sqlite``
    is absolute), or a PostgreSQL database's ``postgresql://USER:PASS@HOST:PORT/DB``
    (shared by replicas), kept whole. Opens nothing.

    Raises StoreError for a URL of another scheme or one that names no file.
    """
    if location.startswith(("postgresql://", "postgres://")):
        return "postgresql", location
    path = location
    if location.startswith(SQLITE_SCHEME):
        path = location.removeprefix(SQLITE_SCHEME).removeprefix("/")
    elif "://" in location:
        scheme = location.partition("://")[0]
        raise StoreError(
            f"store {location!r}: unknown scheme {scheme!r}; known: sqlite, postgresql"
        )
    if not path:
        raise StoreError(f"store {location!r}: no file named")
    return "sqlite", path


#: How long a database store's call waits for a connection by default, s (then 503).
STORE_TIMEOUT_S = 5.0


def open_store(location: str, timeout_s: float = STORE_TIMEOUT_S) -> EventStore:
    """The store at `location` (`store_address`); a database's calls wait `timeout_s` for
    it (a file's do not wait).

    Raises StoreError for a URL of another scheme, or a file the store refuses.
    """
    kind, address = store_address(location)
    # Each implementation is imported when chosen: another database brings its driver.
    if kind == "postgresql":
        from focustrack_estimator.postgres_store import PostgresStore

        return PostgresStore(address, timeout_s=timeout_s)
    from focustrack_estimator.sqlite_store import SQLiteStore

    return SQLiteStore(address)


def json_object(text: object, slide_id: str, sequence: int | None) -> dict[str, Any]:
    """The JSON object stored as `text`; CorruptLogError naming the record if it is none."""
    try:
        value = json.loads(text) if isinstance(text, str | bytes) else None
    except ValueError as error:
        raise CorruptLogError(slide_id, sequence, f"not JSON: {error}") from None
    if not isinstance(value, dict):
        raise CorruptLogError(slide_id, sequence, "not a JSON object")
    return value


def slide_record(row: Sequence[Any]) -> SlideRecord:
    """The record of a row (id, config, created_s, updated_s, n_events, n_accepted, done)."""
    slide_id, config, created_s, updated_s, n_events, n_accepted, done = row
    return SlideRecord(
        slide_id,
        json_object(config, slide_id, None),
        created_s,
        updated_s,
        n_events,
        n_accepted,
        bool(done),
    )
