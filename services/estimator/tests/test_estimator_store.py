"""The estimator's SQLite store beyond the `EventStore` contract (test_event_store.py): its
file (WAL, schema versions), its URL, and SQLite's errors as the store's own."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from focustrack_estimator.event_store import (
    CorruptLogError,
    CorruptSnapshotError,
    Event,
    StoreError,
    StoreFullError,
    StoreUnavailableError,
    open_store,
)
from focustrack_estimator.sqlite_store import SCHEMA_VERSION, SQLiteStore

CONFIG = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 3}}


def _event(sequence: int, z_um: float) -> Event:
    return Event(sequence, {"index": sequence}, {"z_um": z_um}, {"posterior_um": z_um})


def test_committed_events_survive_a_new_connection(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    first = SQLiteStore(path)
    first.create_slide("a", CONFIG)
    for sequence in range(5):
        first.append("a", _event(sequence, float(sequence)), accepted=True, done=False)
    # Read from an independent connection while the first is still open (no close, no
    # checkpoint): what `append` returned from is visible, as after a crash.
    second = SQLiteStore(path)
    assert [e.outcome["posterior_um"] for e in second.events("a")] == [0.0, 1.0, 2.0, 3.0, 4.0]
    second.close()
    first.close()
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_a_path_or_a_sqlite_url_opens_the_same_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    by_path = open_store("relative.sqlite")
    by_path.create_slide("a", CONFIG)
    by_path.close()
    for location in ("sqlite:///relative.sqlite", f"sqlite:///{tmp_path}/relative.sqlite"):
        by_url = open_store(location)
        assert not by_url.created and [s.id for s in by_url.slides()] == ["a"], location
        by_url.close()
    assert f"sqlite:///{tmp_path}".startswith("sqlite:////")  # an absolute path: four slashes


@pytest.mark.parametrize(
    ("location", "message"),
    [
        ("mysql://db/estimator", "unknown scheme .mysql.; known: sqlite, postgresql"),
        ("sqlite://", "no file named"),
        ("/no/such/folder/estimator.sqlite", "cannot be opened"),
    ],
)
def test_a_store_that_cannot_be_opened_says_why(location: str, message: str) -> None:
    with pytest.raises(StoreError, match=message):
        open_store(location)


def test_sqlites_errors_are_the_stores_own(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    store = SQLiteStore(path)
    store.create_slide("a", CONFIG)
    with sqlite3.connect(path) as db:  # damage behind the store's back
        db.execute("DROP TABLE snapshots")
    try:
        with pytest.raises(StoreUnavailableError, match="no such table: snapshots"):
            store.snapshot("a")
        with pytest.raises(StoreUnavailableError):
            store.put_snapshot("a", 1, b"state")
        store.append("a", _event(0, 1.0), accepted=True, done=False)  # the rest still works
    finally:
        store.close()


# --- schema versions ---

_VERSION_1 = """
CREATE TABLE slides (
    id TEXT PRIMARY KEY, config TEXT NOT NULL, created_s REAL NOT NULL, updated_s REAL NOT NULL,
    n_events INTEGER NOT NULL DEFAULT 0, n_accepted INTEGER NOT NULL DEFAULT 0,
    done INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE events (
    slide_id TEXT NOT NULL REFERENCES slides(id) ON DELETE CASCADE,
    sequence INTEGER NOT NULL, acquisition TEXT NOT NULL, measurement TEXT NOT NULL,
    outcome TEXT NOT NULL, recorded_s REAL NOT NULL, PRIMARY KEY (slide_id, sequence)
) WITHOUT ROWID;
INSERT INTO slides VALUES ('old', '{"strategy": "kf-wiener0"}', 1.0, 2.0, 1, 1, 0);
INSERT INTO events VALUES ('old', 0, '{"index": 0}', '{"z_um": 1.0}', '{"accepted": true}', 2.0);
"""


def test_a_file_without_a_schema_version_is_migrated_and_keeps_its_slides(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as db:  # as the estimator wrote it before schema versions
        db.executescript(_VERSION_1)
    store = SQLiteStore(path)
    try:
        assert store.schema_version == SCHEMA_VERSION == 3
        record = store.slide("old")
        assert record is not None and record.n_events == 1
        assert [e.measurement for e in store.events("old")] == [{"z_um": 1.0}]
        store.put_snapshot("old", 1, b"state")
        assert store.snapshot("old") == (1, b"state")
    finally:
        store.close()
    reopened = SQLiteStore(path)  # migrating twice changes nothing
    try:
        assert reopened.snapshot("old") == (1, b"state")
    finally:
        reopened.close()


def test_a_file_of_a_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(StoreError, match="schema version 4"):
        SQLiteStore(path)


def test_a_version_2_snapshot_is_migrated_without_a_checksum_and_not_used(tmp_path: Path) -> None:
    path = tmp_path / "v2.sqlite"
    store = SQLiteStore(path)
    store.create_slide("a", CONFIG)
    store.put_snapshot("a", 1, b"state")
    store.close()
    with sqlite3.connect(path) as db:  # as schema version 2 wrote it: no checksum column
        db.execute("ALTER TABLE snapshots DROP COLUMN sha256")
        db.execute("PRAGMA user_version = 2")
    store = SQLiteStore(path)
    try:
        assert store.schema_version == 3
        with pytest.raises(CorruptSnapshotError, match="no checksum"):
            store.snapshot("a")
        store.put_snapshot("a", 2, b"newer")  # the next one written has its checksum
        assert store.snapshot("a") == (2, b"newer")
    finally:
        store.close()


# --- what the store reads back ---


@pytest.mark.parametrize(
    ("column", "value"),
    [("state", b"other bytes"), ("n_events", 2), ("sha256", "0" * 64), ("slide_id", "b")],
)
def test_a_snapshot_that_does_not_match_its_checksum_is_refused(
    tmp_path: Path, column: str, value: object
) -> None:
    path = tmp_path / "estimator.sqlite"
    store = SQLiteStore(path)
    try:
        store.create_slide("a", CONFIG)
        store.create_slide("b", CONFIG)
        store.put_snapshot("a", 1, b"state")
        with sqlite3.connect(path) as db:  # changed behind the store's back
            db.execute(f"UPDATE snapshots SET {column} = ?", (value,))
        owner = "b" if column == "slide_id" else "a"  # a snapshot moved to another slide
        with pytest.raises(CorruptSnapshotError, match="does not match its checksum"):
            store.snapshot(owner)
    finally:
        store.close()


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", "null"])
def test_a_log_record_that_does_not_decode_is_a_corrupt_log(tmp_path: Path, text: str) -> None:
    path = tmp_path / "estimator.sqlite"
    store = SQLiteStore(path)
    try:
        store.create_slide("a", CONFIG)
        for sequence in range(3):
            store.append("a", _event(sequence, 1.0), accepted=True, done=False)
        with sqlite3.connect(path) as db:
            db.execute("UPDATE events SET measurement = ? WHERE sequence = 1", (text,))
        with pytest.raises(CorruptLogError, match="log record 1 is corrupt") as raised:
            store.events("a")
        assert raised.value.slide_id == "a" and raised.value.sequence == 1
        assert store.events("a", start=2)[0].sequence == 2  # the records after it still read
    finally:
        store.close()


# --- a full disk ---


def _fill(store: SQLiteStore) -> None:
    """Let the store's file grow no more: SQLite answers SQLITE_FULL to a write that needs a
    new page, as on a full disk (`PRAGMA max_page_count` cannot go below the pages in use)."""
    with store._connection() as db:
        db.execute("PRAGMA max_page_count = 1")


def _free(store: SQLiteStore) -> None:
    with store._connection() as db:
        db.execute("PRAGMA max_page_count = 1073741823")


def test_a_full_disk_refuses_the_write_keeps_nothing_and_reads_go_on(tmp_path: Path) -> None:
    store = SQLiteStore(tmp_path / "estimator.sqlite")
    try:
        store.create_slide("a", CONFIG)
        store.append("a", _event(0, 1.0), accepted=True, done=False)
        _fill(store)
        big = Event(1, {"index": 1, "pad": "x" * 20_000}, {"z_um": 2.0}, {"posterior_um": 2.0})
        with pytest.raises(StoreFullError, match="database or disk is full"):
            store.append("a", big, accepted=True, done=False)
        assert store.problem() is not None and "full" in store.problem()  # type: ignore[operator]
        with pytest.raises(StoreFullError):
            store.put_snapshot("a", 1, b"s" * 20_000)
        assert [e.sequence for e in store.events("a")] == [0]  # nothing of it was kept
        assert store.slide("a").n_events == 1  # type: ignore[union-attr]
        _free(store)
        store.append("a", big, accepted=True, done=False)  # the same append, once there is space
        assert store.problem() is None
        assert [e.sequence for e in store.events("a")] == [0, 1]
    finally:
        store.close()
