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
