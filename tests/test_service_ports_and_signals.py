"""The REST services' ports and their end: a port in use is one line (exit 2) before the
service says where it is, and SIGTERM (`docker stop`) ends them gracefully, their bus
closed and their last line logged, and so does Ctrl-C (real processes, loopback)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from focustrack_core.wire.session import free_port, loopback_endpoint

pytestmark = pytest.mark.slow  # services in processes

SERVE = [sys.executable, "-m", "focustrack", "serve"]


def peer(service: str, port: int, tmp_path: Path) -> list[str]:
    """`focustrack serve SERVICE` alone on loopback, its REST API on `port`."""
    if service == "estimator":
        return [*SERVE, service, "--port", str(port), "--store", str(tmp_path / "e.sqlite")]
    bus = ["--mode", "peer", "--listen", loopback_endpoint()]
    return [*SERVE, service, *bus, "--port", str(port)]


@pytest.mark.parametrize("service", ["estimator", "focus", "phase"])
def test_a_rest_port_in_use_is_one_line_before_the_service_says_where_it_is(
    service: str, tmp_path: Path
) -> None:
    """It used to say "... on http://127.0.0.1:PORT", then exit with uvicorn's status 3
    (and the estimator had made its store)."""
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        done = subprocess.run(
            peer(service, port, tmp_path), capture_output=True, text=True, timeout=120
        )
    said = done.stdout + done.stderr
    assert done.returncode == 2, said
    assert f"server cannot listen on 127.0.0.1:{port}: Address already in use" in said
    assert f"http://127.0.0.1:{port}" not in said and "Traceback" not in said
    assert not (tmp_path / "e.sqlite").exists()


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.parametrize(("service", "last_line"), [("focus", "published"), ("phase", "published")])
def test_sigterm_or_ctrl_c_ends_a_service_gracefully(
    http: httpx.Client, service: str, last_line: str, stop: signal.Signals, tmp_path: Path
) -> None:
    """uvicorn raises the signal again after its graceful shutdown: the focus and phase
    services used to die of SIGTERM (status -15), and of Ctrl-C in a traceback, before
    closing their bus."""
    port = free_port()
    process = subprocess.Popen(
        peer(service, port, tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline_s = time.monotonic() + 120
        while True:
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline_s, f"no {service} service on port {port}"
            try:
                http.get(f"http://127.0.0.1:{port}/healthz", timeout=2.0)
                break
            except httpx.TransportError:
                time.sleep(0.2)
        process.send_signal(stop)
        out, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 0, err
    assert last_line in out + err and "Traceback" not in err


@pytest.mark.parametrize("service", ["focus", "phase", "instrument"])
def test_a_zenoh_listen_port_in_use_is_one_line_not_a_wait_for_ever(
    service: str, tmp_path: Path
) -> None:
    """Zenoh fails at each attempt to listen on a port in use: the services that wait for
    their bus retried for ever, logging "the Zenoh router does not answer"."""
    with socket.create_server(("127.0.0.1", 0)) as taken:
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        rest = [] if service == "instrument" else ["--port", str(free_port())]
        command = [*SERVE, service, "--mode", "peer", "--listen", endpoint, *rest]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    said = done.stdout + done.stderr
    assert done.returncode == 2, said
    assert f"(--listen {endpoint}) server cannot listen" in said and "Traceback" not in said
