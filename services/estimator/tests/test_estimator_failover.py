"""Failover: two estimator replicas on one PostgreSQL database behind HAProxy.

A scan goes through the balancer (round robin: consecutive requests land on both
replicas); one replica is killed with SIGKILL in the middle. The scan finishes on the
other, and its maps are exactly the local replay's: no acknowledged measurement lost,
none taken twice into the filter. HAProxy (Debian's package) is installed with apt-get
when missing and the tests run as root; elsewhere the test skips, saying why.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from subprocess import Popen
from typing import NamedTuple

import httpx
import pytest
from estimator_in_process import SETTINGS, local_map, maps
from postgres_server import PostgresServer, ensure_debian_package

from focustrack_client import EstimatorClient
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_core.wire.session import free_port
from focustrack_estimator.event_store import open_store
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.service import spawn

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

STRATEGY = "kf-wiener0"
START_TIMEOUT_S = 120.0

#: The balancer: round robin over the replicas, each checked every 300 ms on /healthz (a
#: replica whose store is degraded is taken out: it would only answer 503), a request that
#: cannot connect sent to the other.
HAPROXY_CONFIG = """
global
    maxconn 256
defaults
    mode http
    timeout connect 1s
    timeout client 30s
    timeout server 30s
    retries 2
    option redispatch
frontend estimators
    bind 127.0.0.1:{port}
    default_backend replicas
backend replicas
    balance roundrobin
    # each request balanced on its own, not the client's keep-alive connection's first
    option http-server-close
    option httpchk GET /healthz
    http-check expect string '"status":"ok"'
{servers}
"""


class Balanced(NamedTuple):
    url: str  # the balancer's
    replicas: list[Popen]
    ports: list[int]  # the replicas'
    database: str  # the URL of their PostgreSQL database


@pytest.fixture
def balanced(http: httpx.Client, postgres: PostgresServer, tmp_path: Path) -> Iterator[Balanced]:
    """Two replicas on a new database, behind HAProxy."""
    haproxy = ensure_debian_package("haproxy", lambda: shutil.which("haproxy"))
    database = postgres.new_database()
    ports = [free_port(), free_port()]
    replicas = [spawn(database, port, timeout_s=START_TIMEOUT_S) for port in ports]
    servers = "\n".join(
        f"    server replica{i} 127.0.0.1:{port} check inter 300ms fall 1 rise 2"
        for i, port in enumerate(ports)
    )
    port = free_port()
    config = tmp_path / "haproxy.cfg"
    config.write_text(HAPROXY_CONFIG.format(port=port, servers=servers))
    balancer = subprocess.Popen([haproxy, "-db", "-f", str(config)], stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while True:
        try:
            if http.get(f"{url}/healthz").status_code == 200:
                break
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, "haproxy did not start"
        time.sleep(0.2)
    yield Balanced(url, replicas, ports, database)
    balancer.terminate()
    balancer.wait(timeout=10)
    for replica in replicas:
        if replica.poll() is None:
            replica.terminate()
            replica.wait(timeout=10)


def _scan_requests(http: httpx.Client, port: int) -> float:
    """The /v1 requests a replica has answered (its /metrics)."""
    text = http.get(f"http://127.0.0.1:{port}/metrics").text
    return sum(
        float(line.rpartition(" ")[2])
        for line in text.splitlines()
        if line.startswith("focustrack_estimator_requests_total") and 'route="/v1' in line
    )


def test_a_replica_killed_mid_scan_loses_nothing(http: httpx.Client, balanced: Balanced) -> None:
    _, measured = maps(seed=7)
    with EstimatorClient(balanced.url) as estimator:
        slide = estimator.create_slide(to_api.slide_create(STRATEGY, SETTINGS))
        n_posted = 0
        while not (step := estimator.next(slide.id)).done:
            if n_posted == 10:  # both replicas have served; one dies with no shutdown
                # round robin: /next on one replica right after /measurements on the other
                assert all(_scan_requests(http, port) >= 10 for port in balanced.ports)
                balanced.replicas[0].send_signal(signal.SIGKILL)
                balanced.replicas[0].wait(timeout=10)
            acquisition = to_domain.acquisition(step)
            assert acquisition is not None
            z_um = measured[acquisition.row, acquisition.col]
            body = to_api.measurement_in(acquisition, simulated_measurement(acquisition, z_um))
            estimator.measure(slide.id, body)
            n_posted += 1
        served = estimator.focus_map_file(slide.id, "npy")
    local = local_map(STRATEGY, SETTINGS, seed=7)
    kept = focus_map_of_npy(served)
    for name in ("posterior_um", "posterior_sigma_um", "z_used_um"):
        assert (getattr(kept, name) == getattr(local, name)).all(), name
    store = open_store(balanced.database)
    try:
        assert [event.sequence for event in store.events(slide.id)] == list(range(n_posted))
    finally:
        store.close()
