"""The store trusts nothing it did not check: tampered snapshots give way to the log, a corrupt
log record stops its slide alone, and a full disk is a 507 that loses nothing."""

from __future__ import annotations

import io
import json
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    slide_config,
)

from focustrack_client import models as api
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_core.serving import BackgroundServer
from focustrack_estimator.app import create_app
from focustrack_estimator.event_store import snapshot_digest
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.sqlite_store import SQLiteStore

STRATEGY = "kf-wiener1"
SEED = 5

# --- tampered snapshots --------------------------------------------------------------


def _arrays(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as archive:
        return {key: archive[key] for key in archive.files}


def _blob(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def _tree(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    return json.loads(arrays["__tree__"].tobytes())


def _with_tree(arrays: dict[str, np.ndarray], tree: dict[str, Any]) -> dict[str, np.ndarray]:
    return {**arrays, "__tree__": np.frombuffer(json.dumps(tree).encode(), np.uint8)}


def _shifted(blob: bytes) -> bytes:
    """The map's heights 50 um higher (every value within its bounds)."""
    arrays = _arrays(blob)
    layers = _tree(arrays)["state"]["map"]["v"]
    keys = [layers[name]["a"] for name in ("prior_um", "posterior_um", "z_used_um")]
    return _blob({**arrays, **{key: arrays[key] + 50.0 for key in keys}})


def _resized(blob: bytes) -> bytes:
    """Every 2-D float array one row and one column larger."""
    arrays = _arrays(blob)
    grow = {k: np.pad(a, ((0, 1), (0, 1))) for k, a in arrays.items() if a.ndim == 2}
    return _blob({**arrays, **grow})


def _renumbered(blob: bytes) -> bytes:
    """The pending acquisition's numbers changed in the JSON tree: tile (5, 12), z -60 m."""
    arrays = _arrays(blob)
    tree = _tree(arrays)
    pending = tree["state"]["_pending"]["v"]
    pending["row"], pending["col"] = {"v": 5}, {"v": 12}
    pending["z"]["v"]["low_um"] = {"v": -60_748_327.0}
    return _blob(_with_tree(arrays, tree))


def _corrupted(blob: bytes) -> bytes:
    """One byte changed, the checksum left as it was."""
    return blob[:100] + bytes([blob[100] ^ 0xFF]) + blob[101:]


def _replace_snapshot(path: Path, slide_id: str, change: Callable[[bytes], bytes]) -> None:
    """Change the slide's snapshot; its checksum is recomputed (as a forger would) except for
    `_corrupted`, which tests the checksum itself."""
    with sqlite3.connect(path) as db:
        n_events, state, digest = db.execute(
            "SELECT n_events, state, sha256 FROM snapshots WHERE slide_id = ?", (slide_id,)
        ).fetchone()
        changed = change(state)
        assert changed != state
        if change is not _corrupted:
            digest = snapshot_digest(slide_id, n_events, changed)
        db.execute(
            "UPDATE snapshots SET state = ?, sha256 = ? WHERE slide_id = ?",
            (changed, digest, slide_id),
        )


@pytest.mark.parametrize("change", [_shifted, _resized, _renumbered, _corrupted])
@pytest.mark.parametrize("n_pairs", [10, 12])  # 12: two events after the snapshot at 10
def test_a_tampered_snapshot_gives_way_to_the_log(
    tmp_path: Path, change: Callable[[bytes], bytes], n_pairs: int
) -> None:
    path = tmp_path / "estimator.sqlite"
    _, measured_um = maps(SEED)

    async def start() -> str:
        with estimator(path, snapshot_every=5) as app:
            async with client(app) as http:
                slide_id = await create(http, STRATEGY)
                await scan(http, slide_id, measured_um, limit=n_pairs)
        return slide_id

    slide_id = run(start())
    _replace_snapshot(path, slide_id, change)

    async def restart() -> tuple[list[int], str, Any]:
        with estimator(path, snapshot_every=5) as app:
            async with client(app) as http:
                statuses = [(await http.get(f"/v1/slides/{slide_id}/next")).status_code]
                await scan(http, slide_id, measured_um)  # to the end, from the log's state
                metrics = (await http.get("/metrics")).text
                return statuses, metrics, await served_map(http, slide_id)

    statuses, metrics, served = run(restart())
    assert statuses == [200]
    assert "focustrack_estimator_snapshots_discarded_total 1.0" in metrics.splitlines()
    assert_same_maps(served, local_map(STRATEGY, SETTINGS, SEED))
    # The snapshot found wanting was replaced by one of the log's state.
    store = SQLiteStore(path)
    try:
        assert store.snapshot(slide_id) is not None
    finally:
        store.close()


def test_a_state_that_fails_under_a_request_is_rebuilt_from_the_log(tmp_path: Path) -> None:
    """A snapshot whose every check passes but whose filter would fail on the next measurement
    (its covariance resized, a forged checksum): that request is done on the log's state."""
    path = tmp_path / "estimator.sqlite"
    _, measured_um = maps(SEED)

    async def start() -> str:
        with estimator(path, snapshot_every=5) as app:
            async with client(app) as http:
                slide_id = await create(http, STRATEGY)
                await scan(http, slide_id, measured_um, limit=10)
        return slide_id

    slide_id = run(start())

    def inner_resized(blob: bytes) -> bytes:
        arrays = _arrays(blob)
        square = [k for k, a in arrays.items() if a.ndim == 2 and a.shape[0] == a.shape[1] > 1]
        assert square, "the filter keeps a covariance"
        return _blob({**arrays, **{k: np.eye(arrays[k].shape[0] + 1) for k in square}})

    _replace_snapshot(path, slide_id, inner_resized)

    async def restart() -> Any:
        with estimator(path) as app:
            async with client(app) as http:
                await scan(http, slide_id, measured_um)
                return await served_map(http, slide_id)

    assert_same_maps(run(restart()), local_map(STRATEGY, SETTINGS, SEED))


# --- a corrupt log record --------------------------------------------------------------


@pytest.mark.parametrize(
    ("column", "value"),
    [
        ("measurement", "{not json"),
        ("measurement", '{"z_um": 1e300, "sigma_um": null, "flags": []}'),
        ("acquisition", '{"index": 3}'),
        ("outcome", "[]"),
    ],
)
def test_a_corrupt_log_record_stops_its_slide_alone(
    tmp_path: Path, column: str, value: str
) -> None:
    path = tmp_path / "estimator.sqlite"
    _, measured_um = maps(SEED)

    async def start() -> tuple[str, str]:
        with estimator(path) as app:
            async with client(app) as http:
                broken, whole = await create(http, STRATEGY), await create(http, STRATEGY)
                for slide_id in (broken, whole):
                    await scan(http, slide_id, measured_um, limit=6)
        return broken, whole

    broken, whole = run(start())
    with sqlite3.connect(path) as db:
        db.execute(
            f"UPDATE events SET {column} = ? WHERE slide_id = ? AND sequence = 3", (value, broken)
        )

    async def restart() -> tuple[list[httpx.Response], Any]:
        with estimator(path) as app:
            async with client(app) as http:
                replies = [
                    await http.get(f"/v1/slides/{broken}/next"),
                    await http.get(f"/v1/slides/{broken}/map"),
                    await http.get(f"/v1/slides/{broken}"),  # its record is whole
                ]
                await scan(http, whole, measured_um)
                return replies, await served_map(http, whole)

    (next_reply, map_reply, record_reply), served = run(restart())
    for reply in (next_reply, map_reply):
        assert reply.status_code == 409, reply.text
        assert reply.json()["code"] == "slide_log_corrupt"
        assert f"slide {broken!r}: its stored log record 3 is corrupt" in reply.json()["detail"]
    assert record_reply.status_code == 200
    assert_same_maps(served, local_map(STRATEGY, SETTINGS, SEED))


# --- a full disk, through a real server ---------------------------------------------


def _set_max_pages(store: SQLiteStore, pages: int) -> None:
    """`PRAGMA max_page_count` on the store's connection: below the pages in use it stops at
    them, and a write that needs one more page gets SQLITE_FULL, as on a full disk."""
    with store._connection() as db:
        db.execute(f"PRAGMA max_page_count = {pages}")


def _measurement(step: dict[str, Any], measured_um: np.ndarray) -> dict[str, Any]:
    acquisition = to_domain.acquisition(api.Next.model_validate(step))
    assert acquisition is not None
    measurement = simulated_measurement(acquisition, measured_um[acquisition.row, acquisition.col])
    return to_api.measurement_in(acquisition, measurement).model_dump(mode="json")


def test_a_full_disk_is_a_507_reads_go_on_and_a_retry_succeeds(tmp_path: Path) -> None:
    store = SQLiteStore(tmp_path / "estimator.sqlite", checkpoint_every_s=0.05)
    _, measured_um = maps(SEED)
    try:
        with BackgroundServer(create_app(store, EstimatorSettings(snapshot_every=10**6))) as server:
            http = httpx.Client(base_url=server.url, timeout=30.0)
            created = http.post("/v1/slides", json=slide_config(STRATEGY, SETTINGS))
            assert created.status_code == 201, created.text
            slide_id = created.json()["id"]
            _set_max_pages(store, 1)  # the disk is full from now on
            full = None
            for _ in range(40):  # until a measurement needs a page the store cannot have
                step = http.get(f"/v1/slides/{slide_id}/next").json()
                body = _measurement(step, measured_um)
                reply = http.post(f"/v1/slides/{slide_id}/measurements", json=body)
                if reply.status_code != 200:
                    full = reply
                    break
            assert full is not None, "the store never filled up"
            assert full.status_code == 507, full.text
            assert full.json()["code"] == "storage_full"
            assert "database or disk is full" in full.json()["detail"]
            assert full.headers["Retry-After"] == "30"
            # Reads go on, and the refused measurement was not logged.
            n_logged = body["sequence"]
            assert http.get(f"/v1/slides/{slide_id}").json()["n_acquisitions"] == n_logged
            assert http.get(f"/v1/slides/{slide_id}/next").json()["sequence"] == n_logged
            assert http.get(f"/v1/slides/{slide_id}/map").status_code == 200
            assert http.get("/healthz").json()["status"] == "degraded"
            assert "focustrack_estimator_store_degraded 1.0" in http.get("/metrics").text
            _set_max_pages(store, 1_073_741_823)  # space again
            again = http.post(f"/v1/slides/{slide_id}/measurements", json=body)
            assert again.status_code == 200, again.text
            assert http.get("/healthz").json()["status"] == "ok"
            assert store._checkpointer.is_alive()
            while (step := http.get(f"/v1/slides/{slide_id}/next").json())["done"] is False:
                reply = http.post(
                    f"/v1/slides/{slide_id}/measurements", json=_measurement(step, measured_um)
                )
                assert reply.status_code == 200, reply.text
            served = http.get(f"/v1/slides/{slide_id}/map", params={"format": "npy"})
            assert_same_maps(focus_map_of_npy(served.content), local_map(STRATEGY, SETTINGS, SEED))
    finally:
        store.close()
