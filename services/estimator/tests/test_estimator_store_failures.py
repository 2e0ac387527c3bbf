"""What the API answers when its store fails under a request, or holds what this version
refuses: the error shape of every reply, never a bare 500 nor a crash."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import httpx
from estimator_in_process import client, create, estimator, maps, run, scan

from focustrack_estimator.app import create_app
from focustrack_estimator.event_store import Event, StoreUnavailableError
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.sqlite_store import SQLiteStore


class FullDisk(SQLiteStore):
    """A store whose appends fail as a full disk makes them fail."""

    def append(self, slide_id: str, event: Event, *, accepted: bool, done: bool) -> None:
        raise StoreUnavailableError(f"store {self.path}: database or disk is full")


def test_a_store_that_fails_under_a_write_is_a_503_to_ask_again(tmp_path: Path) -> None:
    store = FullDisk(tmp_path / "full.sqlite")
    try:
        app = create_app(store, EstimatorSettings())

        async def go() -> httpx.Response:
            async with client(app) as http:
                slide_id = await create(http)
                step = (await http.get(f"/v1/slides/{slide_id}/next")).json()
                body = {"row": step["row"], "col": step["col"], "sequence": 0, "z_um": 0.0}
                return await http.post(f"/v1/slides/{slide_id}/measurements", json=body)

        response = run(go())
    finally:
        store.close()
    assert response.status_code == 503 and response.headers["Retry-After"] == "5"
    assert response.json()["code"] == "internal"
    assert "disk is full" in response.json()["detail"]


def test_stored_parameters_this_version_refuses_are_a_replay_mismatch(tmp_path: Path) -> None:
    path = tmp_path / "estimator.sqlite"
    with estimator(path) as app:
        _, measured_um = maps(seed=3)

        async def first() -> str:
            async with client(app) as http:
                slide_id = await create(http, "kf-wiener1")
                await scan(http, slide_id, measured_um, limit=3)
                return slide_id

        slide_id = run(first())
    # An older version stored a parameter this one refuses (a negative sigma).
    with sqlite3.connect(path) as db:
        (text,) = db.execute("SELECT config FROM slides WHERE id = ?", (slide_id,)).fetchone()
        config = json.loads(text)
        config["params"]["slope_sigma_um_per_tile"] = -0.5
        db.execute("UPDATE slides SET config = ? WHERE id = ?", (json.dumps(config), slide_id))
    with estimator(path) as app:

        async def again() -> httpx.Response:
            async with client(app) as http:
                return await http.get(f"/v1/slides/{slide_id}/next")

        response = run(again())
    assert response.status_code == 500, response.text
    assert response.json()["code"] == "replay_mismatch"
    assert "slope_sigma_um_per_tile" in response.json()["detail"]


def test_a_stored_configuration_this_version_refuses_stops_that_slide_not_the_listing(
    tmp_path: Path,
) -> None:
    """A slide stored by another version (a field this one does not know) made the whole
    listing a 500, and that slide's own requests a 500 or a 422 with no location."""
    path = tmp_path / "estimator.sqlite"

    async def make() -> list[str]:
        with estimator(path) as app:
            async with client(app) as http:
                return [await create(http) for _ in range(3)]

    first, other, last = run(make())
    with sqlite3.connect(path) as db:
        (text,) = db.execute("SELECT config FROM slides WHERE id = ?", (other,)).fetchone()
        config = {**json.loads(text), "colour": "red"}
        db.execute("UPDATE slides SET config = ? WHERE id = ?", (json.dumps(config), other))

    async def read() -> tuple[httpx.Response, httpx.Response, httpx.Response]:
        with estimator(path) as app:
            async with client(app) as http:
                return (
                    await http.get("/v1/slides"),
                    await http.get(f"/v1/slides/{other}"),
                    await http.get(f"/v1/slides/{other}/next"),
                )

    listed, slide, pending = run(read())
    assert listed.status_code == 200, listed.text
    assert [s["id"] for s in listed.json()] == [first, last]
    assert listed.headers["X-Unreadable-Slides"] == other
    for response in (slide, pending):
        assert response.status_code == 409, response.text
        assert response.json()["code"] == "slide_log_corrupt"
        assert "colour" in response.json()["detail"]


class SnapshotsFail(SQLiteStore):
    """A store whose snapshots fail (as a database gone away), counting the attempts."""

    attempts = 0

    def put_snapshot(self, slide_id: str, n_events: int, state: bytes) -> None:
        SnapshotsFail.attempts += 1
        raise StoreUnavailableError(f"store {self.path}: couldn't get a connection")


def test_the_snapshots_at_shutdown_stop_at_the_first_store_failure(tmp_path: Path) -> None:
    """Each slide waited out the store's timeout in turn: minutes to stop a replica whose
    database was gone, past any container's stop timeout."""
    store = SnapshotsFail(tmp_path / "estimator.sqlite")
    try:
        app = create_app(store, EstimatorSettings(snapshot_every=1000))

        async def go() -> None:
            async with client(app) as http:
                for _ in range(3):
                    await scan(http, await create(http), maps(3)[1], limit=2)

        run(go())
        app.state.slides.save_snapshots()  # what the service does at shutdown
    finally:
        store.close()
    assert SnapshotsFail.attempts == 1
