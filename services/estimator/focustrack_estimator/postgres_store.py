"""The estimator's store on PostgreSQL: an `EventStore` that several estimators share.

``focustrack serve estimator --store postgresql://USER:PASS@HOST:PORT/DB``: the
database exists; the store creates and migrates its own tables in it (versioned in
``focustrack_schema``, one migration per version under an advisory lock, so that
replicas starting together migrate once). A database of a newer schema than this
code knows is refused rather than misread.

Replicas: every estimator on the database writes through `append`, which moves a
slide's event count from the sequence it expects to the next in one statement
(``UPDATE ... WHERE n_events = expected``): PostgreSQL's row lock orders two
replicas racing for one sequence, and the second finds the count moved on
(`SequenceConflictError`). A slide therefore has one history whatever the number
of replicas. `n_events` is the cheap check a replica makes of its cached slide.

Faults: connections come from a pool (psycopg-pool) opened without waiting, so the
service starts while the database is down. Every call that cannot reach the
database within `timeout_s` raises `StoreUnavailableError` (the service answers 503
with Retry-After) and `problem` says why until a call succeeds again; the pool
reconnects in the background, with no restart. PostgreSQL commits synchronously
(its default ``synchronous_commit``), so an acknowledged append is on the
server's disk. A full disk (SQLSTATE 53100) is `StoreFullError`.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import psycopg
from psycopg import errors
from psycopg.conninfo import conninfo_to_dict
from psycopg_pool import ConnectionPool

from focustrack_estimator.event_store import (
    STORE_TIMEOUT_S,
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

#: Each version's schema change, applied in order to bring an older database up to date.
#: JSON is kept as the text written (as in SQLite), checked again when it is read.
_MIGRATIONS: dict[int, str] = {
    1: """
CREATE TABLE slides (
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    created_s DOUBLE PRECISION NOT NULL,
    updated_s DOUBLE PRECISION NOT NULL,
    n_events INTEGER NOT NULL DEFAULT 0,
    n_accepted INTEGER NOT NULL DEFAULT 0,
    done BOOLEAN NOT NULL DEFAULT FALSE
);
CREATE INDEX slides_by_creation ON slides (created_s, id);
CREATE TABLE events (
    slide_id TEXT NOT NULL REFERENCES slides(id) ON DELETE CASCADE,
    sequence INTEGER NOT NULL,
    acquisition TEXT NOT NULL,
    measurement TEXT NOT NULL,
    outcome TEXT NOT NULL,
    recorded_s DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (slide_id, sequence)
);
CREATE TABLE snapshots (
    slide_id TEXT PRIMARY KEY REFERENCES slides(id) ON DELETE CASCADE,
    n_events INTEGER NOT NULL,
    state BYTEA NOT NULL,
    created_s DOUBLE PRECISION NOT NULL,
    sha256 TEXT NOT NULL
);
""",
}

#: The schema version this code writes.
SCHEMA_VERSION = max(_MIGRATIONS)

#: The key of the advisory lock that migrations hold (any constant the database's other
#: users do not take: the bytes of "focustra").
_MIGRATION_LOCK = int.from_bytes(b"focustra", "big") & 0x7FFF_FFFF_FFFF_FFFF

#: How often an unreachable database is tried again in the background, s.
PROBE_EVERY_S = 1.0

#: How long the pool keeps trying to open one connection (backing off) before it gives up
#: that attempt and the next call starts another, s.
RECONNECT_TIMEOUT_S = 30.0

_RECORD = "SELECT id, config, created_s, updated_s, n_events, n_accepted, done FROM slides"


def redacted(conninfo: str) -> str:
    """The database's address without its password: ``postgresql://USER@HOST:PORT/DB``."""
    try:
        parts = conninfo_to_dict(conninfo)
    except psycopg.ProgrammingError:
        return "postgresql://(unreadable address)"
    user = f"{parts['user']}@" if parts.get("user") else ""
    port = f":{parts['port']}" if parts.get("port") else ""
    return f"postgresql://{user}{parts.get('host', '')}{port}/{parts.get('dbname', '')}"


class PostgresStore:
    """An `EventStore` in the PostgreSQL database at `conninfo` (a URL or a libpq string).

    `timeout_s`: how long a call waits for a connection before it raises
    `StoreUnavailableError`; `max_connections`: the pool's size (the service's worker
    threads share it). Raises StoreError at once only for an address that cannot be
    read; a database that is down is found (and said) by the calls.
    """

    def __init__(
        self, conninfo: str, *, timeout_s: float = STORE_TIMEOUT_S, max_connections: int = 8
    ) -> None:
        self.address = redacted(conninfo)
        try:
            conninfo_to_dict(conninfo)
        except psycopg.ProgrammingError as error:
            raise StoreError(f"store {self.address}: {error}") from None
        self.timeout_s = timeout_s
        self.created = False  # set when this store creates the schema
        self._failure: str | None = None  # why the last call failed to reach the database
        self._schema_lock = threading.Lock()
        self._schema_ready = False
        self._pool = ConnectionPool(
            conninfo,
            min_size=1,
            max_size=max_connections,
            open=False,
            timeout=timeout_s,
            reconnect_timeout=RECONNECT_TIMEOUT_S,
            # UTF8 whatever the database's encoding: on an SQL_ASCII database psycopg would
            # otherwise return text as bytes (and compare it with text: "text = bytea")
            kwargs={"connect_timeout": max(1, round(timeout_s)), "client_encoding": "utf8"},
            check=ConnectionPool.check_connection,  # a connection the server dropped is replaced
            name="focustrack-estimator",
        )
        self._pool.open(wait=False)
        try:
            with self._transaction():
                pass  # migrate now if the database is up; if not, the first call will
        except StoreUnavailableError as error:
            log.warning("%s; the estimator starts and retries", error)
        self._closing = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, daemon=True)
        self._watchdog.start()

    def _watch(self) -> None:
        """While the database is unreachable, try it every `PROBE_EVERY_S`: `problem` (the
        service's /healthz) clears when it answers again, with no request needed."""
        while not self._closing.wait(PROBE_EVERY_S):
            if self._failure is None:
                continue
            try:
                with self._transaction():
                    pass
            except StoreError:
                continue  # still down (and said), or a newer schema: the calls say which

    @contextmanager
    def _transaction(self) -> Iterator[psycopg.Connection[Any]]:
        """A pooled connection in one transaction (committed when the block ends, rolled back
        if it raises); psycopg's failures raised as StoreUnavailableError (StoreFullError
        for a full disk), and the store's state (`problem`) set by how the call ended."""
        try:
            with self._pool.connection() as connection:
                if not self._schema_ready:
                    self._migrate(connection)
                with connection.transaction():
                    yield connection
        except errors.DiskFull as error:
            raise self._failed(StoreFullError(f"store {self.address}: {error}")) from error
        except (psycopg.OperationalError, psycopg.InterfaceError) as error:
            raise self._failed(StoreUnavailableError(f"store {self.address}: {error}")) from error
        if self._failure is not None:
            log.warning("store %s: reachable again", self.address)
            self._failure = None

    def _failed(self, failure: StoreUnavailableError) -> StoreUnavailableError:
        self._failure = str(failure)
        return failure

    def _migrate(self, connection: psycopg.Connection[Any]) -> None:
        """Bring the database to `SCHEMA_VERSION`, each migration atomic, once among replicas
        (an advisory lock); StoreError for a schema newer than this code."""
        with self._schema_lock, connection.transaction():
            if self._schema_ready:
                return
            connection.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATION_LOCK,))
            connection.execute("CREATE TABLE IF NOT EXISTS focustrack_schema (version INTEGER)")
            row = connection.execute("SELECT max(version) FROM focustrack_schema").fetchone()
            version = row[0] if row is not None and row[0] is not None else 0
            if version > SCHEMA_VERSION:
                raise StoreError(
                    f"store {self.address} has schema version {version}; this estimator "
                    f"knows up to {SCHEMA_VERSION}: run a newer one"
                )
            for target in range(version + 1, SCHEMA_VERSION + 1):
                connection.execute(_MIGRATIONS[target])  # several statements: simple protocol
                connection.execute("INSERT INTO focustrack_schema VALUES (%s)", (target,))
            self.created = version == 0
            self._schema_ready = True

    def problem(self) -> str | None:
        """Why the store is degraded (its last call could not reach the database), or None."""
        return self._failure

    @property
    def schema_version(self) -> int:
        with self._transaction() as db:
            row = db.execute("SELECT max(version) FROM focustrack_schema").fetchone()
        return 0 if row is None else int(row[0])

    def close(self) -> None:
        """Close the pool's connections (once; later calls do nothing)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._watchdog.join()
        self._pool.close()

    def create_slide(self, slide_id: str, config: dict[str, Any]) -> SlideRecord:
        now_s = time.time()
        try:
            with self._transaction() as db:
                db.execute(
                    "INSERT INTO slides (id, config, created_s, updated_s) VALUES (%s, %s, %s, %s)",
                    (slide_id, json.dumps(config), now_s, now_s),
                )
        except errors.UniqueViolation as error:
            raise StoreError(f"slide {slide_id!r} already exists") from error
        return SlideRecord(slide_id, config, now_s, now_s, 0, 0, False)

    def slide(self, slide_id: str) -> SlideRecord | None:
        with self._transaction() as db:
            row = db.execute(f"{_RECORD} WHERE id = %s", (slide_id,)).fetchone()
        return None if row is None else slide_record(row)

    def n_events(self, slide_id: str) -> int | None:
        with self._transaction() as db:
            row = db.execute("SELECT n_events FROM slides WHERE id = %s", (slide_id,)).fetchone()
        return None if row is None else int(row[0])

    def slides(self) -> list[SlideRecord]:
        with self._transaction() as db:
            rows = db.execute(f"{_RECORD} ORDER BY created_s, id").fetchall()
        return [slide_record(row) for row in rows]

    def slides_after(self, after: tuple[float, str] | None, limit: int) -> list[SlideRecord]:
        created_s, slide_id = after if after is not None else (float("-inf"), "")
        with self._transaction() as db:
            rows = db.execute(
                f"{_RECORD} WHERE (created_s, id) > (%s, %s) ORDER BY created_s, id LIMIT %s",
                (created_s, slide_id, limit),
            ).fetchall()
        return [slide_record(row) for row in rows]

    def count_slides(self) -> int:
        with self._transaction() as db:
            row = db.execute("SELECT count(*) FROM slides").fetchone()
        return 0 if row is None else int(row[0])

    def delete_slide(self, slide_id: str) -> bool:
        with self._transaction() as db:
            cursor = db.execute("DELETE FROM slides WHERE id = %s", (slide_id,))
        return cursor.rowcount > 0

    def append(self, slide_id: str, event: Event, *, accepted: bool, done: bool) -> None:
        """Log `event` as the slide's next one and update its progress in one transaction.

        The count moves only from `event.sequence` (``WHERE n_events = expected``), so of
        two replicas appending the same sequence the second finds it moved:
        SequenceConflictError with the current count; StoreError if there is no slide.
        """
        now_s = time.time()
        with self._transaction() as db:
            moved = db.execute(
                "UPDATE slides SET n_events = n_events + 1, n_accepted = n_accepted + %s, "
                "done = %s, updated_s = %s WHERE id = %s AND n_events = %s RETURNING id",
                (int(accepted), done, now_s, slide_id, event.sequence),
            ).fetchone()
            if moved is None:
                row = db.execute(
                    "SELECT n_events FROM slides WHERE id = %s", (slide_id,)
                ).fetchone()
                if row is None:
                    raise StoreError(f"no slide {slide_id!r}")
                raise SequenceConflictError(slide_id, event.sequence, int(row[0]))
            db.execute(
                "INSERT INTO events "
                "(slide_id, sequence, acquisition, measurement, outcome, recorded_s) "
                "VALUES (%s, %s, %s, %s, %s, %s)",
                (
                    slide_id,
                    event.sequence,
                    json.dumps(event.acquisition),
                    json.dumps(event.measurement),
                    json.dumps(event.outcome),
                    now_s,
                ),
            )

    def events(self, slide_id: str, start: int = 0) -> list[Event]:
        with self._transaction() as db:
            rows = db.execute(
                "SELECT sequence, acquisition, measurement, outcome FROM events "
                "WHERE slide_id = %s AND sequence >= %s ORDER BY sequence",
                (slide_id, start),
            ).fetchall()
        return [
            Event(sequence, *(json_object(text, slide_id, sequence) for text in texts))
            for sequence, *texts in rows
        ]

    def put_snapshot(self, slide_id: str, n_events: int, state: bytes) -> None:
        digest = snapshot_digest(slide_id, n_events, state)
        try:
            with self._transaction() as db:
                db.execute(
                    "INSERT INTO snapshots (slide_id, n_events, state, created_s, sha256) "
                    "VALUES (%s, %s, %s, %s, %s) "
                    "ON CONFLICT (slide_id) DO UPDATE SET n_events = excluded.n_events, "
                    "state = excluded.state, created_s = excluded.created_s, "
                    "sha256 = excluded.sha256 "
                    "WHERE excluded.n_events >= snapshots.n_events",
                    (slide_id, n_events, state, time.time(), digest),
                )
        except errors.ForeignKeyViolation as error:
            raise StoreError(f"no slide {slide_id!r}") from error

    def snapshot(self, slide_id: str) -> Snapshot | None:
        with self._transaction() as db:
            row = db.execute(
                "SELECT n_events, state, sha256 FROM snapshots WHERE slide_id = %s", (slide_id,)
            ).fetchone()
        if row is None:
            return None
        return checked_snapshot(slide_id, int(row[0]), bytes(row[1]), row[2])

    def replace_config(self, slide_id: str, config: dict[str, Any]) -> None:
        with self._transaction() as db:
            row = db.execute(
                "SELECT n_events FROM slides WHERE id = %s FOR UPDATE", (slide_id,)
            ).fetchone()
            if row is None:
                raise StoreError(f"no slide {slide_id!r}")
            if row[0] != 0:
                raise SequenceConflictError(slide_id, 0, int(row[0]))
            db.execute(
                "UPDATE slides SET config = %s, updated_s = %s WHERE id = %s",
                (json.dumps(config), time.time(), slide_id),
            )
            db.execute("DELETE FROM snapshots WHERE slide_id = %s", (slide_id,))
