"""The `EventStore` contract, checked on every implementation (a new one joins `STORES`).

What the live slides rely on: slides and their progress, an append only at the
sequence it expects (a `SequenceConflictError` naming the current one otherwise,
as when another replica wrote first), ordered log reads, the newest snapshot, delete,
and everything still there when the store is opened again.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from focustrack_estimator.event_store import (
    Event,
    EventStore,
    SequenceConflictError,
    Snapshot,
    StoreError,
)
from focustrack_estimator.postgres_store import PostgresStore
from focustrack_estimator.sqlite_store import SQLiteStore

#: Each implementation, opened on a test's folder or database (opening it again: the same
#: store); PostgreSQL's tests run on a real server (`conftest.postgres`), on a database of
#: the server's encoding and on one made SQL_ASCII (which stores bytes, not characters).
STORES = ("postgresql", "postgresql-sql_ascii", "sqlite")

CONFIG = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 3}}

OpenStore = Callable[[], EventStore]


def _event(sequence: int, z_um: float | None = 1.0) -> Event:
    return Event(
        sequence,
        {"index": sequence, "row": 0, "col": sequence},
        {"z_um": z_um, "sigma_um": None, "flags": []},
        {"accepted": z_um is not None, "posterior_um": z_um},
    )


@pytest.fixture(params=STORES)
def open_store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[OpenStore]:
    """Open the test's store (again); each one opened is closed after the test."""
    opened: list[EventStore] = []
    if request.param.startswith("postgresql"):
        encoding = "SQL_ASCII" if request.param.endswith("sql_ascii") else None
        url = request.getfixturevalue("postgres").new_database(encoding)

    def open_() -> EventStore:
        if request.param.startswith("postgresql"):
            opened.append(PostgresStore(url))
        else:
            opened.append(SQLiteStore(tmp_path / "estimator.sqlite"))
        return opened[-1]

    yield open_
    for store in opened:
        store.close()


@pytest.fixture
def store(open_store: OpenStore) -> EventStore:
    return open_store()


def test_slides_are_created_read_listed_and_counted(store: EventStore) -> None:
    created = store.create_slide("a", CONFIG)
    store.create_slide("b", {**CONFIG, "strategy": "tile-skip"})
    a = store.slide("a")
    assert a == created and a.config == CONFIG
    assert (a.n_events, a.n_accepted, a.done) == (0, 0, False)
    assert [s.id for s in store.slides()] == ["a", "b"]  # oldest first
    assert store.count_slides() == 2
    assert store.slide("zzz") is None and store.events("zzz") == []
    with pytest.raises(StoreError, match="already exists"):
        store.create_slide("a", CONFIG)


def test_text_beyond_ascii_comes_back_as_written(store: EventStore) -> None:
    config = {**CONFIG, "note": "z in µm, Ø 25 mm"}
    store.create_slide("slide-µ", config)
    store.append("slide-µ", _event(0), accepted=True, done=False)
    record = store.slide("slide-µ")
    assert record is not None and record.id == "slide-µ" and record.config == config
    assert [record.id for record in store.slides()] == ["slide-µ"]
    assert store.n_events("slide-µ") == 1 and store.events("slide-µ") == [_event(0)]


def test_appends_at_the_expected_sequence_log_events_and_progress(store: EventStore) -> None:
    store.create_slide("a", CONFIG)
    store.append("a", _event(0), accepted=True, done=False)
    store.append("a", _event(1, None), accepted=False, done=True)
    record = store.slide("a")
    assert record is not None and (record.n_events, record.n_accepted, record.done) == (2, 1, True)
    assert record.updated_s >= record.created_s
    assert store.events("a") == [_event(0), _event(1, None)]
    assert (store.n_events("a"), store.n_events("no such slide")) == (2, None)


def test_an_append_where_the_log_is_not_is_a_conflict_naming_the_current_sequence(
    store: EventStore,
) -> None:
    store.create_slide("a", CONFIG)
    with pytest.raises(SequenceConflictError, match="expects event 0, got 1") as ahead:
        store.append("a", _event(1), accepted=True, done=False)
    assert (ahead.value.slide_id, ahead.value.expected, ahead.value.current) == ("a", 1, 0)
    store.append("a", _event(0), accepted=True, done=False)
    with pytest.raises(SequenceConflictError) as behind:  # another writer had logged 0
        store.append("a", _event(0, 2.0), accepted=True, done=True)
    assert (behind.value.expected, behind.value.current) == (0, 1)
    record = store.slide("a")
    assert record is not None and (record.n_events, record.done) == (1, False)  # nothing of it
    assert store.events("a") == [_event(0)]


def test_an_append_to_no_slide_is_refused(store: EventStore) -> None:
    with pytest.raises(StoreError, match="no slide") as refused:
        store.append("nope", _event(0), accepted=True, done=False)
    assert not isinstance(refused.value, SequenceConflictError)


def test_writers_racing_for_one_sequence_leave_one_event(open_store: OpenStore) -> None:
    """Replicas sharing slides: each appends what it computed; one wins, the others reload."""
    stores = [open_store() for _ in range(2)]  # two connections, as two replicas have
    stores[0].create_slide("a", CONFIG)
    errors: list[SequenceConflictError] = []
    barrier = threading.Barrier(8)

    def write(writer: int) -> None:
        barrier.wait()
        try:
            stores[writer % 2].append("a", _event(0, float(writer)), accepted=True, done=False)
        except SequenceConflictError as error:
            errors.append(error)

    threads = [threading.Thread(target=write, args=(writer,)) for writer in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(errors) == 7 and {error.current for error in errors} == {1}
    (logged,) = stores[1].events("a")
    assert logged.sequence == 0


def test_appends_to_many_slides_from_many_threads_keep_each_log_whole(store: EventStore) -> None:
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


def test_the_log_is_read_in_order_from_a_sequence(store: EventStore) -> None:
    store.create_slide("a", CONFIG)
    for sequence in range(5):
        store.append("a", _event(sequence, float(sequence)), accepted=True, done=False)
    assert [e.sequence for e in store.events("a", start=3)] == [3, 4]
    assert store.events("a", start=5) == []
    assert [e.outcome["posterior_um"] for e in store.events("a")] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_the_newest_snapshot_is_kept(store: EventStore) -> None:
    store.create_slide("a", CONFIG)
    assert store.snapshot("a") is None
    store.put_snapshot("a", 5, b"five")
    store.put_snapshot("a", 9, b"nine")
    store.put_snapshot("a", 7, b"seven")  # older than the one kept: ignored
    assert store.snapshot("a") == Snapshot(9, b"nine")
    with pytest.raises(StoreError, match="no slide"):
        store.put_snapshot("nope", 1, b"state")


def test_delete_forgets_the_slide_its_log_and_its_snapshot(store: EventStore) -> None:
    store.create_slide("a", CONFIG)
    store.append("a", _event(0), accepted=True, done=False)
    store.put_snapshot("a", 1, b"state")
    assert store.delete_slide("a")
    assert not store.delete_slide("a")
    assert store.slide("a") is None and store.events("a") == [] and store.snapshot("a") is None
    assert store.count_slides() == 0
    store.create_slide("a", CONFIG)  # the id is free again, with an empty log
    assert store.events("a") == [] and store.snapshot("a") is None


def test_everything_survives_opening_the_store_again(open_store: OpenStore) -> None:
    first = open_store()
    assert first.created
    first.create_slide("a", CONFIG)
    for sequence in range(3):
        first.append("a", _event(sequence), accepted=True, done=sequence == 2)
    first.put_snapshot("a", 2, b"state")
    before = first.slide("a")
    first.close()
    first.close()  # a second close does nothing
    again = open_store()
    assert not again.created
    assert again.slide("a") == before
    assert again.events("a") == [_event(0), _event(1), _event(2)]
    assert again.snapshot("a") == Snapshot(2, b"state")
