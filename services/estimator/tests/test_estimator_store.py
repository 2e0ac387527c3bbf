"""The estimator's SQLite store: slides, ordered event logs, durability across connections."""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from focustrack_estimator.store import SCHEMA_VERSION, Event, Store, StoreError

CONFIG = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 3}}


def _event(sequence: int, z_um: float | None = 1.0) -> Event:
    return Event(
        sequence,
        {"index": sequence, "row": 0, "col": sequence},
        {"z_um": z_um, "sigma_um": None, "flags": []},
        {"accepted": z_um is not None, "posterior_um": z_um},
    )


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    store = Store(tmp_path / "estimator.sqlite")
    yield store
    store.close()


def test_slides_round_trip_and_progress(store: Store) -> None:
    store.create_slide("a", CONFIG)
    store.create_slide("b", {**CONFIG, "strategy": "tile-skip"})
    store.append("a", _event(0), accepted=True, done=False)
    store.append("a", _event(1, None), accepted=False, done=True)

    a = store.slide("a")
    assert a is not None and a.config == CONFIG
    assert (a.n_events, a.n_accepted, a.done) == (2, 1, True)
    assert [s.id for s in store.slides()] == ["a", "b"]
    assert store.count_slides() == 2
    assert store.events("a") == [_event(0), _event(1, None)]
    assert store.events("b") == [] and store.slide("zzz") is None


def test_log_has_no_gaps_and_no_duplicates(store: Store) -> None:
    store.create_slide("a", CONFIG)
    with pytest.raises(StoreError, match="expects event 0, got 1"):
        store.append("a", _event(1), accepted=True, done=False)
    store.append("a", _event(0), accepted=True, done=False)
    with pytest.raises(StoreError, match="expects event 1, got 0"):
        store.append("a", _event(0), accepted=True, done=False)
    with pytest.raises(StoreError, match="no slide"):
        store.append("nope", _event(0), accepted=True, done=False)
    with pytest.raises(StoreError, match="already exists"):
        store.create_slide("a", CONFIG)
    record = store.slide("a")
    assert record is not None and record.n_events == 1  # the refused appends rolled back
    assert len(store.events("a")) == 1


def test_delete_removes_the_log(store: Store) -> None:
    store.create_slide("a", CONFIG)
    store.append("a", _event(0), accepted=True, done=False)
    assert store.delete_slide("a")
    assert not store.delete_slide("a")
    assert store.slide("a") is None and store.events("a") == []
    store.create_slide("a", CONFIG)  # the id is free again, with an empty log
    assert store.events("a") == []


def test_committed_events_survive_a_new_connection(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    first = Store(path)
    first.create_slide("a", CONFIG)
    for sequence in range(5):
        first.append("a", _event(sequence, float(sequence)), accepted=True, done=False)
    # Read from an independent connection while the first is still open (no close, no
    # checkpoint): what `append` returned from is visible, as after a crash.
    second = Store(path)
    assert [e.outcome["posterior_um"] for e in second.events("a")] == [0.0, 1.0, 2.0, 3.0, 4.0]
    second.close()
    first.close()
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_appends_from_many_threads_keep_each_log_whole(store: Store) -> None:
    slide_ids = [f"s{i}" for i in range(8)]
    for slide_id in slide_ids:
        store.create_slide(slide_id, CONFIG)

    def write(slide_id: str) -> None:
        for sequence in range(25):
            store.append(slide_id, _event(sequence), accepted=True, done=sequence == 24)

    threads = [threading.Thread(target=write, args=(slide_id,)) for slide_id in slide_ids]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for slide_id in slide_ids:
        assert [e.sequence for e in store.events(slide_id)] == list(range(25))
        record = store.slide(slide_id)
        assert record is not None and record.done and record.n_events == 25


# --- schema versions and snapshots ---

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
    store = Store(path)
    try:
        assert store.schema_version == SCHEMA_VERSION == 2
        record = store.slide("old")
        assert record is not None and record.n_events == 1
        assert [e.measurement for e in store.events("old")] == [{"z_um": 1.0}]
        store.put_snapshot("old", 1, b"state")
        assert store.snapshot("old") == (1, b"state")
    finally:
        store.close()
    reopened = Store(path)  # migrating twice changes nothing
    try:
        assert reopened.snapshot("old") == (1, b"state")
    finally:
        reopened.close()


def test_a_file_of_a_newer_schema_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(StoreError, match="schema version 3"):
        Store(path)


def test_the_newest_snapshot_is_kept_and_goes_with_its_slide(store: Store) -> None:
    store.create_slide("a", CONFIG)
    assert store.snapshot("a") is None
    store.put_snapshot("a", 5, b"five")
    store.put_snapshot("a", 9, b"nine")
    store.put_snapshot("a", 7, b"seven")  # older than the one kept: ignored
    assert store.snapshot("a") == (9, b"nine")
    for sequence in range(3):
        store.append("a", _event(sequence), accepted=True, done=False)
    assert [e.sequence for e in store.events("a", start=1)] == [1, 2]
    assert store.delete_slide("a")
    assert store.snapshot("a") is None
