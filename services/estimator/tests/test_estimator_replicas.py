"""Two estimators on one store, as replicas behind a balancer: one history per slide.

Each test runs on a shared SQLite file and on a shared PostgreSQL database (a real server,
`conftest.postgres`). Whatever replica answers: a request sees what another replica
recorded just before (read-your-writes), the same measurement sent to both is taken
once (both answers agree), a different value for a recorded acquisition is the usual
409, and a scan that alternates replicas tile by tile gives exactly the local replay's
maps.
"""

from __future__ import annotations

import asyncio
import io
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
    served_map,
)
from postgres_server import PostgresServer
from tcp_relay import TcpRelay

from focustrack_client import models as api
from focustrack_core.rest import to_api, to_domain
from focustrack_estimator.app import create_app
from focustrack_estimator.event_store import open_store
from focustrack_estimator.postgres_store import PostgresStore
from focustrack_estimator.prior import PRIOR_MEDIA_TYPE
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.settings import EstimatorSettings

STRATEGY = "kf-wiener0"


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """Where both replicas keep their slides."""
    if request.param == "sqlite":
        return str(tmp_path / "estimator.sqlite")
    server: PostgresServer = request.getfixturevalue("postgres")
    return server.new_database()


async def _post_next(http: httpx.AsyncClient, slide_id: str, measured_um: np.ndarray) -> int:
    """Ask for the next acquisition and post its measurement; the sequence posted (-1: done)."""
    response = await http.get(f"/v1/slides/{slide_id}/next")
    assert response.status_code == 200, response.text
    acquisition = to_domain.acquisition(api.Next.model_validate(response.json()))
    if acquisition is None:
        return -1
    measurement = simulated_measurement(acquisition, measured_um[acquisition.row, acquisition.col])
    body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
    response = await http.post(f"/v1/slides/{slide_id}/measurements", json=body)
    assert response.status_code == 200, response.text
    return acquisition.index


def test_a_scan_alternating_replicas_is_the_local_replay(store: str) -> None:
    _, measured = maps(seed=3)

    async def go() -> None:
        with estimator(store) as first, estimator(store) as second:
            async with client(first) as one, client(second) as other:
                slide_id = await create(one, STRATEGY)
                replicas, turn = (one, other), 0
                while await _post_next(replicas[turn % 2], slide_id, measured) >= 0:
                    turn += 1
                assert turn >= SETTINGS.grid.rows * SETTINGS.grid.cols  # remeasures too
                for http in replicas:
                    assert_same_maps(await served_map(http, slide_id), local)

    local = local_map(STRATEGY, SETTINGS, seed=3)
    run(go())


def test_a_measurement_is_seen_by_the_other_replica_at_once(store: str) -> None:
    async def go() -> None:
        with estimator(store) as first, estimator(store) as second:
            async with client(first) as one, client(second) as other:
                slide_id = await create(one, STRATEGY)
                next_url = f"/v1/slides/{slide_id}/next"
                assert (await other.get(next_url)).json()["sequence"] == 0  # cached on `other`
                url = f"/v1/slides/{slide_id}/measurements"
                body = {"row": 0, "col": 0, "sequence": 0, "z_um": 0.5}
                taken = await one.post(url, json=body)
                assert taken.status_code == 200
                assert (await other.get(next_url)).json()["sequence"] == 1  # read-your-writes
                again = await other.post(url, json=body)  # the same value: the same answer
                assert again.status_code == 200 and again.json() == taken.json()
                different = await other.post(url, json={**body, "z_um": 0.7})
                assert different.status_code == 409
                assert "already recorded" in different.json()["detail"]
                deleted = await one.delete(f"/v1/slides/{slide_id}")
                assert deleted.status_code == 204
                assert (await other.get(next_url)).status_code == 404

    run(go())


def test_the_same_measurement_sent_to_both_at_once_is_taken_once(store: str) -> None:
    """Both replicas race for each sequence: one appends, the other loses, reloads the slide
    and answers what was recorded. The log holds each acquisition once."""
    _, measured = maps(seed=4)

    async def go() -> str:
        with estimator(store) as first, estimator(store) as second:
            async with client(first) as one, client(second) as other:
                slide_id = await create(one, STRATEGY)
                url = f"/v1/slides/{slide_id}/measurements"
                for _ in range(8):
                    response = await one.get(f"/v1/slides/{slide_id}/next")
                    pending = api.Next.model_validate(response.json())
                    acquisition = to_domain.acquisition(pending)
                    assert acquisition is not None
                    z_um = measured[acquisition.row, acquisition.col]
                    measurement = simulated_measurement(acquisition, z_um)
                    body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
                    answers = await asyncio.gather(
                        one.post(url, json=body), other.post(url, json=body)
                    )
                    assert [a.status_code for a in answers] == [200, 200], answers[1].text
                    assert answers[0].json() == answers[1].json()
                return slide_id

    slide_id = run(go())
    logged = open_store(store)
    try:
        assert [event.sequence for event in logged.events(slide_id)] == list(range(8))
    finally:
        logged.close()


def test_a_prior_set_through_one_replica_is_used_by_the_other(store: str) -> None:
    truth, _ = maps(seed=5)

    async def go() -> tuple[dict, dict]:
        with estimator(store) as first, estimator(store) as second:
            async with client(first) as one, client(second) as other:
                slide_id = await create(one, "kf-rescan")
                before = (await one.get(f"/v1/slides/{slide_id}/next")).json()  # cached on one
                npy = _npy(np.stack([truth, np.full_like(truth, 0.5)]))
                response = await other.put(
                    f"/v1/slides/{slide_id}/prior",
                    content=npy,
                    headers={"Content-Type": PRIOR_MEDIA_TYPE},
                )
                assert response.status_code == 204, response.text
                return before, (await one.get(f"/v1/slides/{slide_id}/next")).json()

    before, after = run(go())
    assert before["predicted_z_um"] != after["predicted_z_um"]
    assert after["predicted_z_um"] == pytest.approx(truth[after["row"], after["col"]], abs=1e-6)


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def test_a_replica_cut_off_from_the_database_acknowledges_no_write(
    postgres: PostgresServer,
) -> None:
    """No split brain: the replica that cannot reach the database refuses (503) while the
    other goes on, and once reconnected it answers from the history the other wrote."""
    database = postgres.new_database()
    relay = TcpRelay(postgres.port)  # the cut-off replica's only way to the database
    through_relay = database.replace(f":{postgres.port}/", f":{relay.port}/")

    async def go() -> None:
        cut_store = PostgresStore(through_relay, timeout_s=1.0)
        try:
            with estimator(database) as healthy:
                cut_app = create_app(cut_store, EstimatorSettings())
                async with client(cut_app) as cut, client(healthy) as other:
                    slide_id = await create(other, STRATEGY)
                    next_url = f"/v1/slides/{slide_id}/next"
                    assert (await cut.get(next_url)).json()["sequence"] == 0
                    relay.cut()
                    url = f"/v1/slides/{slide_id}/measurements"
                    body = {"row": 0, "col": 0, "sequence": 0, "z_um": 0.5}
                    refused = await cut.post(url, json=body)
                    assert refused.status_code == 503, refused.text
                    assert "Retry-After" in refused.headers
                    assert (await cut.get("/healthz")).json()["status"] == "degraded"
                    assert (await other.post(url, json=body)).status_code == 200
                    relay.restore()
                    for _ in range(50):  # the store's probe runs every second
                        if (await cut.get("/healthz")).json()["status"] == "ok":
                            break
                        await asyncio.sleep(0.2)
                    assert (await cut.get(next_url)).json()["sequence"] == 1
        finally:
            cut_store.close()
            relay.close()

    run(go())
