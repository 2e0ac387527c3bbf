"""The estimator restarted on its store, in process: every slide continues where it was,
from its newest snapshot and the events after it; a log that no longer replays is a 500,
round-off in a replay a warning. And the grid limit of a service's settings."""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import httpx
import numpy as np
import pytest
from estimator_in_process import (
    SETTINGS,
    assert_same_maps,
    client,
    create,
    estimator,
    local_map,
    maps,
    run,
    scan,
    served_map,
)

from focustrack_core.domain import FocusMap
from focustrack_estimator.event_store import Event
from focustrack_estimator.records import outcome_of
from focustrack_estimator.registry import Catalogue
from focustrack_estimator.service import catalogue_from
from focustrack_estimator.slide import Slide
from focustrack_estimator.sqlite_store import SQLiteStore


def test_a_new_app_on_the_same_store_continues_every_slide(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    names = ["kf-wiener1-dir", "survey-bilinear"]
    measured = {name: maps(7 + i)[1] for i, name in enumerate(names)}

    async def first_half() -> dict[str, tuple[str, dict]]:
        with estimator(path) as app:
            async with client(app) as http:
                state = {}
                for name in names:
                    slide_id = await create(http, name)
                    await scan(http, slide_id, measured[name], limit=17)
                    state[name] = (slide_id, (await http.get(f"/v1/slides/{slide_id}/next")).json())
        return state

    async def second_half(state: dict[str, tuple[str, dict]]) -> dict[str, FocusMap]:
        with estimator(path) as app:
            async with client(app) as http:
                result = {}
                for name, (slide_id, pending) in state.items():
                    assert (await http.get(f"/v1/slides/{slide_id}/next")).json() == pending
                    await scan(http, slide_id, measured[name])
                    result[name] = await served_map(http, slide_id)
        return result

    for i, (name, served) in enumerate(run(second_half(run(first_half()))).items()):
        assert_same_maps(served, local_map(name, SETTINGS, 7 + i))


@pytest.mark.parametrize("snapshot_every", [5, 1000], ids=["snapshot", "log alone"])
def test_a_slide_loaded_from_its_store_serves_the_map_the_live_one_did(
    tmp_path: Path, snapshot_every: int
) -> None:
    """The pending tile's prior was missing after a restart, or on another replica."""
    path = tmp_path / "estimator.sqlite"

    async def live() -> tuple[str, FocusMap]:
        with estimator(path, snapshot_every=snapshot_every) as app:
            async with client(app) as http:
                slide_id = await create(http, SNAPSHOTTED)
                await scan(http, slide_id, maps(5)[1], limit=13)
                return slide_id, await served_map(http, slide_id)

    slide_id, served = run(live())
    store = SQLiteStore(path)
    record = store.slide(slide_id)
    assert record is not None
    loaded = Slide.load(record, store, snapshot_every=snapshot_every)
    assert loaded.restored == (snapshot_every == 5)
    assert np.isfinite(served.prior_um).sum() == 14  # the 13 measured and the pending one
    assert_same_maps(loaded.focus_map(), served)
    store.close()


def test_a_log_that_no_longer_replays_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"

    async def start() -> str:
        with estimator(path) as app:
            async with client(app) as http:
                slide_id = await create(http)
                await scan(http, slide_id, maps(2)[1], limit=3)
        return slide_id

    slide_id = run(start())
    with sqlite3.connect(path) as db:  # as if the strategy had changed since
        db.execute(
            "UPDATE events SET outcome = replace(outcome, '\"accepted\": true', "
            "'\"accepted\": false') WHERE sequence = 1"
        )

    async def restart() -> httpx.Response:
        with estimator(path) as app:
            async with client(app) as http:
                response = await http.get(f"/v1/slides/{slide_id}/next")
        return response

    response = run(restart())
    assert response.status_code == 500
    assert "outcome 1 no longer replays" in response.json()["detail"]


def test_a_slide_whose_strategy_is_no_longer_served_is_a_409_naming_the_catalogue(
    tmp_path: Path,
) -> None:
    """A slide made under --strategies-from, the service started again without it: its
    requests were 500s (a log that no longer replays) while nothing had changed but that."""
    path = tmp_path / "estimator.sqlite"
    catalogue = catalogue_from("focustrack.bench.strategies")  # --strategies-from's

    async def start() -> str:
        with estimator(path, catalogue) as app:
            async with client(app) as http:
                slide_id = await create(http, "gp-oracle")
                await scan(http, slide_id, maps(2)[1], limit=3)
        return slide_id

    slide_id = run(start())

    async def restart(served: Catalogue | None) -> httpx.Response:
        with estimator(path, served) as app:
            async with client(app) as http:
                return await http.get(f"/v1/slides/{slide_id}/next")

    refused = run(restart(None))
    assert refused.status_code == 409, refused.text
    assert refused.json()["code"] == "strategy_not_served"
    assert "'gp-oracle', which this estimator does not serve" in refused.json()["detail"]
    assert "--strategies-from" in refused.json()["detail"]
    assert run(restart(catalogue)).status_code == 200  # served again


SNAPSHOTTED = "kf-2d"  # the restart tests' strategy


def _start(path: Path, n_pairs: int, snapshot_every: int) -> str:
    async def go() -> str:
        with estimator(path, snapshot_every=snapshot_every) as app:
            async with client(app) as http:
                slide_id = await create(http, SNAPSHOTTED)
                await scan(http, slide_id, maps(5)[1], limit=n_pairs)
        return slide_id

    return run(go())


def _finish(path: Path, slide_id: str) -> tuple[httpx.Response, object]:
    """Restart on the store: the first /next, then the rest of the scan and its map."""

    async def go() -> tuple[httpx.Response, object]:
        with estimator(path) as app:
            async with client(app) as http:
                first = await http.get(f"/v1/slides/{slide_id}/next")
                if first.status_code != 200:
                    return first, None
                await scan(http, slide_id, maps(5)[1])
                result = await served_map(http, slide_id)
        return first, result

    return run(go())


def _tamper(path: Path, sequence: int, before: str, after: str) -> None:
    with sqlite3.connect(path) as db:
        cursor = db.execute(
            "UPDATE events SET outcome = replace(outcome, ?, ?) WHERE sequence = ?",
            (before, after, sequence),
        )
        assert cursor.rowcount == 1


def test_a_restart_replays_only_the_events_after_the_snapshot(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    slide_id = _start(path, n_pairs=13, snapshot_every=5)
    store = SQLiteStore(path)
    snapshot = store.snapshot(slide_id)
    store.close()
    assert snapshot is not None and snapshot[0] == 10
    # An event the snapshot covers is not replayed (changing it is not noticed) ...
    _tamper(path, 3, '"accepted": true', '"accepted": false')
    first, served = _finish(path, slide_id)
    assert first.status_code == 200
    assert_same_maps(served, local_map(SNAPSHOTTED, SETTINGS, 5))  # type: ignore[arg-type]


def test_a_restart_reads_the_events_a_snapshot_covers_only_when_needed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "estimator.sqlite"
    slide_id = _start(path, n_pairs=13, snapshot_every=5)
    store = SQLiteStore(path)
    logged = store.events(slide_id)
    reads: list[int] = []  # the `start` of every read of the log
    read_events = store.events

    def events(slide_id: str, start: int = 0) -> list[Event]:
        reads.append(start)
        return read_events(slide_id, start)

    monkeypatch.setattr(store, "events", events)
    record = store.slide(slide_id)
    assert record is not None
    slide = Slide.load(record, store, snapshot_every=5)
    # The snapshot covers 10 events: only the last of them (its state is checked against
    # it) and the later ones are read.
    assert reads == [9]
    assert len(slide.history) == len(logged)
    assert slide.history[-1].outcome == outcome_of(logged[-1].outcome)
    assert reads == [9]
    assert slide.history[3].outcome == outcome_of(logged[3].outcome)  # now the rest, once
    assert [entry.outcome for entry in slide.history] == [outcome_of(e.outcome) for e in logged]
    assert reads == [9, 0]
    store.close()


def test_events_after_the_snapshot_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    slide_id = _start(path, n_pairs=13, snapshot_every=5)
    _tamper(path, 11, '"accepted": true', '"accepted": false')
    first, _ = _finish(path, slide_id)
    assert first.status_code == 500
    assert "outcome 11 no longer replays" in first.json()["detail"]


def test_a_snapshot_that_does_not_fit_falls_back_to_the_whole_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "estimator.sqlite"
    slide_id = _start(path, n_pairs=13, snapshot_every=5)
    with sqlite3.connect(path) as db:
        db.execute("UPDATE snapshots SET state = ?", (b"garbage",))
    with caplog.at_level(logging.WARNING):
        first, served = _finish(path, slide_id)
    assert first.status_code == 200
    assert "snapshot not used, replaying its log" in caplog.text
    assert_same_maps(served, local_map(SNAPSHOTTED, SETTINGS, 5))  # type: ignore[arg-type]


def test_round_off_in_a_replayed_outcome_is_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A log written with another numpy or BLAS differs in the last digits: it still loads."""
    path = tmp_path / "estimator.sqlite"
    slide_id = _start(path, n_pairs=4, snapshot_every=1000)  # no snapshot: the whole log replays
    with sqlite3.connect(path) as db:
        (outcome,) = db.execute("SELECT outcome FROM events WHERE sequence = 2").fetchone()
    value = outcome.split('"posterior_um": ')[1].split(",")[0]
    _tamper(path, 2, f'"posterior_um": {value}', f'"posterior_um": {float(value) * (1 + 1e-12)!r}')
    with caplog.at_level(logging.WARNING):
        first, served = _finish(path, slide_id)
    assert first.status_code == 200
    assert "outcome 2 differs from the logged one by round-off only" in caplog.text
    assert_same_maps(served, local_map(SNAPSHOTTED, SETTINGS, 5))  # type: ignore[arg-type]
    # More than round-off is still a mismatch (replayed from the log, the snapshot gone).
    with sqlite3.connect(path) as db:
        db.execute("UPDATE events SET outcome = json_set(outcome, '$.posterior_um', 1.0)")
        db.execute("DELETE FROM snapshots")
    first, _ = _finish(path, slide_id)
    assert first.status_code == 500


def test_a_grid_over_the_service_limit_is_a_422_naming_it(tmp_path: Path) -> None:
    async def go() -> httpx.Response:
        with estimator(tmp_path / "e.sqlite", max_grid_side=8, max_grid_tiles=40) as app:
            async with client(app) as http:
                ok = await create(http, SNAPSHOTTED)  # 6x5: within both limits
                assert ok
                body = {"strategy": SNAPSHOTTED, "grid": {"rows": 9, "cols": 2}}
                too_tall = await http.post("/v1/slides", json=body)
                assert too_tall.status_code == 422
                assert "--max-grid-side" in too_tall.json()["detail"][0]["msg"]
                body = {"strategy": SNAPSHOTTED, "grid": {"rows": 7, "cols": 7}}
                response = await http.post("/v1/slides", json=body)
        return response

    response = run(go())
    assert response.status_code == 422
    detail = response.json()["detail"][0]
    assert detail["loc"] == ["body", "grid"] and "49 tiles" in detail["msg"]
