"""The estimator on PostgreSQL when the database fails: a real server, a real uvicorn process.

Down at start, the estimator starts anyway, says `degraded` on /healthz, answers /v1 with
503 and Retry-After, and serves once the database is back, with no restart. Restarted
(or crashed) mid-scan, nothing acknowledged is lost: the scan, retried through the 503s,
ends with exactly the local replay's maps.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from subprocess import Popen

import httpx
import pytest
from estimator_in_process import SETTINGS, local_map, maps, slide_config
from postgres_server import PostgresServer, ensure_postgresql

from focustrack_client import models as api
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_core.wire.session import free_port
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.service import spawn

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

STRATEGY = "kf-wiener0"
#: Seconds a server may take to start: imports alone took 30-45 s on a loaded 2-core machine.
START_TIMEOUT_S = 120.0
#: Seconds a call waits for the database: less than the default 5, room for a loaded machine.
STORE_TIMEOUT_S = 2.0


@pytest.fixture
def database() -> Iterator[PostgresServer]:
    """A PostgreSQL server of this test's own, initialised but not started (in a folder of
    its own under the temporary folder: pytest's are closed to the postgres user)."""
    with tempfile.TemporaryDirectory(prefix="focustrack-pg-") as folder:
        server = PostgresServer(ensure_postgresql(), Path(folder))
        yield server
        with contextlib.suppress(RuntimeError):  # already stopped
            server.stop("immediate")


@pytest.fixture
def estimator(database: PostgresServer) -> Iterator[tuple[Popen, httpx.Client]]:
    """The estimator on `database`'s default database, started while the database is down;
    a call waits `STORE_TIMEOUT_S` for it (each 503 while it is away costs that much)."""
    port = free_port()
    options = ("--store-timeout-s", str(STORE_TIMEOUT_S))
    process = spawn(database.url(), port, timeout_s=START_TIMEOUT_S, options=options)
    http = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0)
    yield process, http
    http.close()
    process.terminate()
    process.wait(timeout=10)


def _until(check: object, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():  # type: ignore[operator]
        assert time.monotonic() < deadline, "the estimator did not recover in time"
        time.sleep(0.2)


def _retried(send: object) -> httpx.Response:
    """`send()` again while the estimator answers 503 (the database is away)."""
    deadline = time.monotonic() + 60.0
    while (response := send()).status_code == 503:  # type: ignore[operator]
        assert time.monotonic() < deadline
        time.sleep(0.2)
    return response


def test_down_at_start_then_back_without_a_restart(
    database: PostgresServer, estimator: tuple[Popen, httpx.Client]
) -> None:
    _, http = estimator
    assert http.get("/healthz").json()["status"] == "degraded"
    refused = http.post("/v1/slides", json=slide_config(STRATEGY, SETTINGS))
    assert refused.status_code == 503
    assert int(refused.headers["Retry-After"]) > 0
    assert f"couldn't get a connection after {STORE_TIMEOUT_S:.2f} sec" in refused.json()["detail"]

    database.start()
    _until(lambda: http.get("/healthz").json()["status"] == "ok")
    created = http.post("/v1/slides", json=slide_config(STRATEGY, SETTINGS))
    assert created.status_code == 201, created.text


@pytest.mark.parametrize("mode", ["fast", "immediate"])
def test_a_database_restarted_mid_scan_loses_nothing_acknowledged(
    database: PostgresServer, estimator: tuple[Popen, httpx.Client], mode: str
) -> None:
    _, http = estimator
    database.start()
    _until(lambda: http.get("/healthz").json()["status"] == "ok")
    slide_id = _retried(lambda: http.post("/v1/slides", json=slide_config(STRATEGY, SETTINGS)))
    slide_id = slide_id.json()["id"]
    _, measured = maps(seed=6)
    n_posted = 0
    while True:
        if n_posted == 10:  # a third of the way: the database goes away and comes back
            database.stop(mode)
            assert http.get(f"/v1/slides/{slide_id}/next").status_code == 503
            assert http.get("/healthz").json()["status"] == "degraded"
            database.start()
        pending = _retried(lambda: http.get(f"/v1/slides/{slide_id}/next"))
        acquisition = to_domain.acquisition(api.Next.model_validate(pending.json()))
        if acquisition is None:
            break
        measurement = simulated_measurement(acquisition, measured[acquisition.row, acquisition.col])
        body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
        url = f"/v1/slides/{slide_id}/measurements"
        assert _retried(lambda: http.post(url, json=body)).status_code == 200  # noqa: B023
        n_posted += 1
    served = http.get(f"/v1/slides/{slide_id}/map", params={"format": "npy"})
    local = local_map(STRATEGY, SETTINGS, seed=6)
    kept = focus_map_of_npy(served.content)
    for name in ("posterior_um", "posterior_sigma_um", "z_used_um"):
        assert (getattr(kept, name) == getattr(local, name)).all(), name
