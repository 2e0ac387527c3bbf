"""The estimator's embedded store: an `EventStore` in one SQLite file.

Schema versions (``PRAGMA user_version``), migrated forward on open:
1, the slides and their events; 2, the snapshots; 3, each snapshot's checksum
(`snapshot_digest`; a snapshot of version 2 has none and is not used). A file of
a newer version than this code knows is refused rather than misread.

Durability: WAL journal with ``synchronous=FULL``, so a committed event is
on disk (the WAL is fsynced) before `append` returns. One connection is
shared by the service's worker threads behind a lock. An fsync costs 0.2 ms
on an idle development machine but 4-12 ms when other processes write, so
appends are group-committed: those that arrive during a commit share the next.
SQLite's own errors leave this module as `StoreUnavailableError`, a full disk
(SQLITE_FULL) as `StoreFullError`: nothing of that write is kept, and the store says
it is degraded (`problem`) until a write succeeds again. Checkpoints run on a thread
of their own that outlives their failures: it logs each, waits longer after each
(up to `CHECKPOINT_BACKOFF_MAX_S`) and carries on once they succeed again.
"""

from __future__ import annotations

import errno
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from focustrack_estimator.event_store import (
    CorruptSnapshotError,
    Event,
    SequenceConflictError,
    SlideRecord,
    Snapshot,
    StoreError,
    StoreFullError,
    StoreUnavailableError,
    checked_snapshot,
    json_object,
    slide_record,
    snapshot_digest,
)

log = logging.getLogger(__name__)

#: Each version's schema change, applied in order to bring an older file up to date.
_MIGRATIONS: dict[int, str] = {
    1: """
CREATE TABLE IF NOT EXISTS slides (
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    created_s REAL NOT NULL,
    updated_s REAL NOT NULL,
    n_events INTEGER NOT NULL DEFAULT 0,
    n_accepted INTEGER NOT NULL DEFAULT 0,
    done INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS events (
    slide_id TEXT NOT NULL REFERENCES slides(id) ON DELETE CASCADE,
    sequence INTEGER NOT NULL,
    acquisition TEXT NOT NULL,
    measurement TEXT NOT NULL,
    outcome TEXT NOT NULL,
    recorded_s REAL NOT NULL,
    PRIMARY KEY (slide_id, sequence)
) WITHOUT ROWID;
""",
    2: """
CREATE TABLE IF NOT EXISTS snapshots (
    slide_id TEXT PRIMARY KEY REFERENCES slides(id) ON DELETE CASCADE,
    n_events INTEGER NOT NULL,
    state BLOB NOT NULL,
    created_s REAL NOT NULL
);
""",
    3: """
ALTER TABLE snapshots ADD COLUMN sha256 TEXT;
""",
}

#: The size a restarted WAL file is truncated to (``PRAGMA journal_size_limit``).
WAL_SIZE_LIMIT_BYTES = 64 * 1024 * 1024

#: The schema version this code writes (``PRAGMA user_version``).
SCHEMA_VERSION = max(_MIGRATIONS)

#: The longest pause between two checkpoints that failed, s (the pause doubles from the
#: checkpoint period after each failure).
CHECKPOINT_BACKOFF_MAX_S = 30.0


def unavailable(path: str, error: sqlite3.Error | OSError) -> StoreUnavailableError:
    """The store's error for a failure of SQLite or of the file system under it: a
    StoreFullError for a full disk (SQLITE_FULL, ENOSPC, EDQUOT)."""
    full = (
        error.sqlite_errorcode == sqlite3.SQLITE_FULL
        if isinstance(error, sqlite3.Error)
        else error.errno in (errno.ENOSPC, errno.EDQUOT)
    )
    return (StoreFullError if full else StoreUnavailableError)(f"store {path}: {error}")


@dataclass
class _Append:
    """An append waiting in the group-commit queue, and how it ended."""

    slide_id: str
    event: Event
    accepted: bool
    done: bool
    finished: bool = False
    error: Exception | None = None


class SQLiteStore:
    """An `EventStore` in one SQLite file at `path` (created if missing or empty).

    Opening checks the file (``PRAGMA quick_check``): a damaged file, or one that is
    not SQLite, raises StoreError naming it, rather than serving until a read fails.
    `created` says whether the file was missing or empty (a new store).
    """

    def __init__(self, path: str | Path, checkpoint_every_s: float = 1.0) -> None:
        self.path = str(path)
        self.address = self.path
        file = Path(self.path)
        self.created = not file.exists() or file.stat().st_size == 0
        try:  # autocommit mode: every write below opens its own explicit transaction
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        except sqlite3.Error as error:  # no such folder, no permission
            message = f"{self.path} cannot be opened as the estimator's store: {error}"
            raise StoreError(message) from None
        self._lock = threading.Lock()  # the connection, and the one commit under way
        self._full: str | None = None  # why the last write found the disk full
        self._checkpoint_failure: str | None = None  # why the last checkpoint failed
        self._queue_lock = threading.Lock()
        self._queue: list[_Append] = []  # appends waiting for the next group commit
        try:
            self._check()
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            # No checkpoint inside a commit: copying the WAL into the database (and its
            # fsync) stalled every waiting request for 150-200 ms. `_checkpoints` does it.
            self._db.execute("PRAGMA wal_autocheckpoint=0")
            # A WAL that has been copied whole restarts from its beginning but keeps its
            # size: cut it back then. Snapshots of a 200x200 slide (up to 23 MB each) grew
            # it past 500 MB during one scan, disk that a restart's recovery may scan.
            self._db.execute(f"PRAGMA journal_size_limit={WAL_SIZE_LIMIT_BYTES}")
            self._migrate()
        except sqlite3.DatabaseError as error:
            self._db.close()
            raise StoreError(
                f"{self.path} cannot be used as the estimator's store: {error}; "
                "restore it from a backup or move it away to start a new store"
            ) from None
        self._closing = threading.Event()
        self._checkpointer = threading.Thread(
            target=self._checkpoints, args=(checkpoint_every_s,), daemon=True
        )
        self._checkpointer.start()

    def _check(self) -> None:
        """Raise StoreError naming the file if SQLite's quick check finds damage in it."""
        problems = [row[0] for row in self._db.execute("PRAGMA quick_check(5)").fetchall()]
        if problems != ["ok"]:
            self._db.close()
            raise StoreError(
                f"{self.path} is damaged (SQLite quick_check: {'; '.join(problems)}); "
                "refusing to start on it: restore it from a backup or move it away"
            )

    def _migrate(self) -> None:
        """Bring the file to `SCHEMA_VERSION`, one migration per version, each atomic."""
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            self._db.close()
            raise StoreError(
                f"{self.path} has schema version {version}; this estimator knows up to "
                f"{SCHEMA_VERSION}: run a newer one"
            )
        if version == 0 and self._table_exists("slides"):
            version = 1  # written before the schema had a version: version 1's tables
        for target in range(version + 1, SCHEMA_VERSION + 1):
            self._db.execute("BEGIN IMMEDIATE")
            for statement in _MIGRATIONS[target].split(";"):
                if statement.strip():
                    self._db.execute(statement)
            self._db.execute(f"PRAGMA user_version = {target}")
            self._db.execute("COMMIT")

    def _table_exists(self, name: str) -> bool:
        query = "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?"
        return self._db.execute(query, (name,)).fetchone() is not None

    @contextmanager
    def _connection(self, *, writes: bool = False) -> Iterator[sqlite3.Connection]:
        """The shared connection, held alone; SQLite's errors raised as StoreUnavailableError
        (StoreFullError for a full disk). `writes`: the block writes, so its outcome says
        whether the disk is full (`problem`)."""
        with self._lock:
            try:
                yield self._db
            except (sqlite3.Error, OSError) as error:
                failure = unavailable(self.path, error)
                if writes:
                    self._wrote(failure)
                raise failure from error
            if writes:
                self._wrote(None)

    def _wrote(self, failure: StoreUnavailableError | None) -> None:
        """Note how a write ended: a full disk degrades the store until a write succeeds."""
        if isinstance(failure, StoreFullError):
            if self._full is None:
                log.warning("%s; writes are refused until there is space again", failure)
            self._full = str(failure)
        elif failure is None and self._full is not None:
            log.warning("store %s: writes succeed again", self.path)
            self._full = None

    def problem(self) -> str | None:
        """Why the store is degraded (its last write found the disk full, its last
        checkpoint failed), or None while it is well."""
        problems = [p for p in (self._full, self._checkpoint_failure) if p is not None]
        return "; ".join(problems) or None

    @property
    def schema_version(self) -> int:
        with self._connection() as db:
            return db.execute("PRAGMA user_version").fetchone()[0]

    def _checkpoints(self, every_s: float) -> None:
        """Copy committed WAL frames into the database now and then, beside the writers.

        A PASSIVE checkpoint on a connection of its own takes no write lock, so
        commits go on while it copies; the WAL restarts once it has been copied whole.
        A failure (a full disk, an I/O error) is logged and the next attempt waits
        twice as long (at most `CHECKPOINT_BACKOFF_MAX_S`): the thread lives as long
        as the store, or the WAL would grow without bound once the disk has space again.
        """
        pause_s = every_s
        db: sqlite3.Connection | None = None
        while not self._closing.wait(pause_s):
            try:
                db = db or sqlite3.connect(self.path, isolation_level=None)
                db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
            except (sqlite3.Error, OSError) as error:
                pause_s = min(2.0 * pause_s, max(every_s, CHECKPOINT_BACKOFF_MAX_S))
                self._checkpoint_failure = f"checkpoint of store {self.path} failed: {error}"
                log.warning("%s; next attempt in %.3g s", self._checkpoint_failure, pause_s)
                continue
            if self._checkpoint_failure is not None:
                log.warning("store %s: checkpoints succeed again", self.path)
                self._checkpoint_failure = None
            pause_s = every_s
        if db is not None:
            db.close()

    def close(self) -> None:
        """Checkpoint and close (once; later calls do nothing)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._checkpointer.join()
        with self._lock:
            try:  # a full disk leaves the WAL as it is: the next open recovers from it
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            except sqlite3.Error as error:
                log.warning("store %s: last checkpoint failed: %s", self.path, error)
            self._db.close()

    def create_slide(self, slide_id: str, config: dict[str, Any]) -> SlideRecord:
        now_s = time.time()
        with self._connection(writes=True) as db:
            try:
                db.execute(
                    "INSERT INTO slides (id, config, created_s, updated_s) VALUES (?, ?, ?, ?)",
                    (slide_id, json.dumps(config), now_s, now_s),
                )
            except sqlite3.IntegrityError as error:
                raise StoreError(f"slide {slide_id!r} already exists") from error
        return SlideRecord(slide_id, config, now_s, now_s, 0, 0, False)

    def slide(self, slide_id: str) -> SlideRecord | None:
        with self._connection() as db:
            row = db.execute(
                "SELECT id, config, created_s, updated_s, n_events, n_accepted, done "
                "FROM slides WHERE id = ?",
                (slide_id,),
            ).fetchone()
        return None if row is None else slide_record(row)

    def n_events(self, slide_id: str) -> int | None:
        with self._connection() as db:
            row = db.execute("SELECT n_events FROM slides WHERE id = ?", (slide_id,)).fetchone()
        return None if row is None else row[0]

    def slides(self) -> list[SlideRecord]:
        """Every slide, oldest first."""
        with self._connection() as db:
            rows = db.execute(
                "SELECT id, config, created_s, updated_s, n_events, n_accepted, done "
                "FROM slides ORDER BY created_s, id"
            ).fetchall()
        return [slide_record(row) for row in rows]

    def slides_after(self, after: tuple[float, str] | None, limit: int) -> list[SlideRecord]:
        """At most `limit` slides, oldest first, those after `after` (created_s, id) only."""
        # The first page: after every slide (no creation time is below -inf).
        created_s, slide_id = after if after is not None else (float("-inf"), "")
        with self._connection() as db:
            rows = db.execute(
                "SELECT id, config, created_s, updated_s, n_events, n_accepted, done "
                "FROM slides WHERE (created_s, id) > (?, ?) ORDER BY created_s, id LIMIT ?",
                (created_s, slide_id, limit),
            ).fetchall()
        return [slide_record(row) for row in rows]

    def count_slides(self) -> int:
        with self._connection() as db:
            return db.execute("SELECT count(*) FROM slides").fetchone()[0]

    def delete_slide(self, slide_id: str) -> bool:
        """Forget a slide, its log and its snapshot; False if there was no such slide."""
        with self._connection(writes=True) as db:
            cursor = db.execute("DELETE FROM slides WHERE id = ?", (slide_id,))
        return cursor.rowcount > 0

    def append(self, slide_id: str, event: Event, *, accepted: bool, done: bool) -> None:
        """Log `event` as the slide's next one and update its progress, durably, atomically.

        The sequence must be the slide's event count (the log has no gaps): else a
        SequenceConflictError. Group commit: appends from concurrent threads that
        queue while a commit is under way go to disk together in the next
        transaction, one fsync for all of them; each returns once its own event is
        committed.
        """
        ticket = _Append(slide_id, event, accepted, done)
        with self._queue_lock:
            self._queue.append(ticket)
        with self._lock:
            if not ticket.finished:  # nobody committed it yet: commit everything queued
                with self._queue_lock:
                    batch, self._queue = self._queue, []
                self._commit(batch)
        if ticket.error is not None:
            raise ticket.error

    def _commit(self, batch: list[_Append]) -> None:
        """One transaction for the batch; a refused append (a savepoint) spares the others.

        If the transaction fails (a full disk), every append of the batch fails with it:
        none was committed, none is acknowledged.
        """
        now_s = time.time()
        failed: StoreUnavailableError | None = None
        try:
            self._db.execute("BEGIN IMMEDIATE")
            for ticket in batch:
                self._db.execute("SAVEPOINT append")
                try:
                    self._insert(ticket, now_s)
                except StoreError as error:
                    self._db.execute("ROLLBACK TO append")
                    ticket.error = error
                self._db.execute("RELEASE append")
            self._db.execute("COMMIT")
        except (sqlite3.Error, OSError) as error:
            failed = unavailable(self.path, error)
            self._roll_back()
            for ticket in batch:
                ticket.error = failed  # a refusal in its savepoint was rolled back too
        finally:
            for ticket in batch:
                ticket.finished = True
        self._wrote(failed)

    def _roll_back(self) -> None:
        """End a failed transaction, if SQLite has not already (it rolls back by itself after
        some errors, a full disk among them); a rollback that fails too is logged."""
        if not self._db.in_transaction:
            return
        try:
            self._db.execute("ROLLBACK")
        except sqlite3.Error as error:
            log.warning("store %s: rollback of a failed commit failed: %s", self.path, error)

    def _insert(self, ticket: _Append, now_s: float) -> None:
        slide_id, event = ticket.slide_id, ticket.event
        row = self._db.execute("SELECT n_events FROM slides WHERE id = ?", (slide_id,)).fetchone()
        if row is None:
            raise StoreError(f"no slide {slide_id!r}")
        if event.sequence != row[0]:
            raise SequenceConflictError(slide_id, event.sequence, row[0])
        self._db.execute(
            "INSERT INTO events "
            "(slide_id, sequence, acquisition, measurement, outcome, recorded_s) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            (
                slide_id,
                event.sequence,
                json.dumps(event.acquisition),
                json.dumps(event.measurement),
                json.dumps(event.outcome),
                now_s,
            ),
        )
        self._db.execute(
            "UPDATE slides SET n_events = n_events + 1, n_accepted = n_accepted + ?, "
            "done = ?, updated_s = ? WHERE id = ?",
            (int(ticket.accepted), int(ticket.done), now_s, slide_id),
        )

    def put_snapshot(self, slide_id: str, n_events: int, state: bytes) -> None:
        """Keep `state` as the slide's snapshot after its first `n_events` events (replacing
        an older one); a snapshot older than the one kept is ignored. StoreError if there
        is no such slide."""
        digest = snapshot_digest(slide_id, n_events, state)
        with self._connection(writes=True) as db:
            try:
                db.execute(
                    "INSERT INTO snapshots (slide_id, n_events, state, created_s, sha256) "
                    "VALUES (?, ?, ?, ?, ?) "
                    "ON CONFLICT (slide_id) DO UPDATE SET n_events = excluded.n_events, "
                    "state = excluded.state, created_s = excluded.created_s, "
                    "sha256 = excluded.sha256 "
                    "WHERE excluded.n_events >= snapshots.n_events",
                    (slide_id, n_events, state, time.time(), digest),
                )
            except sqlite3.IntegrityError as error:  # the slide's foreign key
                raise StoreError(f"no slide {slide_id!r}") from error

    def snapshot(self, slide_id: str) -> Snapshot | None:
        """The slide's newest snapshot, or None; CorruptSnapshotError if its checksum does not
        match what it holds (or it has none: written by schema version 2)."""
        with self._connection() as db:
            row = db.execute(
                "SELECT n_events, state, sha256 FROM snapshots WHERE slide_id = ?", (slide_id,)
            ).fetchone()
        if row is None:
            return None
        n_events, state, digest = row
        if not isinstance(n_events, int) or not isinstance(state, bytes):
            raise CorruptSnapshotError(f"slide {slide_id!r}: its snapshot's row is malformed")
        return checked_snapshot(slide_id, n_events, state, digest)

    def replace_config(self, slide_id: str, config: dict[str, Any]) -> None:
        """Replace the configuration of a slide whose log is empty and forget its snapshot,
        in one transaction; SequenceConflictError if events are logged, StoreError if there
        is no such slide."""
        with self._connection() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                row = db.execute("SELECT n_events FROM slides WHERE id = ?", (slide_id,)).fetchone()
                if row is None:
                    raise StoreError(f"no slide {slide_id!r}")
                if row[0] != 0:
                    raise SequenceConflictError(slide_id, 0, row[0])
                db.execute(
                    "UPDATE slides SET config = ?, updated_s = ? WHERE id = ?",
                    (json.dumps(config), time.time(), slide_id),
                )
                db.execute("DELETE FROM snapshots WHERE slide_id = ?", (slide_id,))
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    def events(self, slide_id: str, start: int = 0) -> list[Event]:
        """The slide's log in sequence order, from sequence `start` on."""
        with self._connection() as db:
            rows = db.execute(
                "SELECT sequence, acquisition, measurement, outcome FROM events "
                "WHERE slide_id = ? AND sequence >= ? ORDER BY sequence",
                (slide_id, start),
            ).fetchall()
        return [
            Event(sequence, *(json_object(text, slide_id, sequence) for text in texts))
            for sequence, *texts in rows
        ]
