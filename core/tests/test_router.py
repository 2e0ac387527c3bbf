"""The router entry point (the `zenoh` service where the official image is absent): a real
process on a free loopback port routes two client sessions, and stops cleanly on SIGTERM."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh

from focustrack_core.wire import codec
from focustrack_core.wire.session import loopback_endpoint, open_session


def test_the_router_routes_clients_and_stops_on_sigterm() -> None:
    endpoint = loopback_endpoint()
    command = [sys.executable, "-m", "focustrack_core.wire.router"]
    router = subprocess.Popen(
        [*command, "--listen", endpoint, "--no-multicast-scouting"],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        received = threading.Event()
        # Two clients: they see each other only through the router (docs in wire/session.py).
        with (
            open_session(connect=[endpoint]) as subscriber,
            open_session(connect=[endpoint]) as pub,
        ):
            subscriber.declare_subscriber("test/router", lambda sample: received.set())
            for _ in range(50):  # until the subscription has reached the router
                pub.put("test/router", b"hello")
                if received.wait(0.1):
                    break
        assert received.is_set()
        router.send_signal(signal.SIGTERM)
        _, stderr = router.communicate(timeout=10)
        assert router.returncode == 0, stderr
        assert f"listening on {endpoint}" in stderr and "stopped by SIGTERM" in stderr
    finally:
        router.kill()


def test_the_router_needs_an_endpoint() -> None:
    run = subprocess.run(
        [sys.executable, "-m", "focustrack_core.wire.router"], capture_output=True, text=True
    )
    assert run.returncode == 2 and "--listen" in run.stderr


@pytest.mark.parametrize("shared_memory", [True, False])
def test_the_router_hands_on_shared_memory_only_when_told(shared_memory: bool) -> None:
    endpoint = loopback_endpoint()
    flags = ["--shared-memory"] if shared_memory else []
    router = subprocess.Popen(
        [sys.executable, "-m", "focustrack_core.wire.router", "--listen", endpoint, *flags],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        arrived: list[bool] = []  # whether each payload came as shared memory
        received = threading.Event()

        def on_sample(sample: zenoh.Sample) -> None:
            arrived.append(sample.payload.as_shm() is not None)
            received.set()

        with (
            open_session(connect=[endpoint], shared_memory=True) as subscriber,
            open_session(connect=[endpoint], shared_memory=True) as pub,
        ):
            subscriber.declare_subscriber("test/pixels", on_sample)
            publisher = codec.PixelPublisher(pub, shm_pool_bytes=1 << 20)
            pixels = codec.pixel_array((64, 64), np.uint16)
            for _ in range(50):  # until the subscription has reached the router
                pub.put("test/pixels", publisher.payload(pixels))
                if received.wait(0.1):
                    break
        assert arrived and publisher.n_shared >= 1
        assert arrived[0] is shared_memory
    finally:
        router.kill()
        router.wait(timeout=10)


def test_two_routers_connected_to_each_other_route_between_their_clients_after_a_kill() -> None:
    """A client of each router sees the other's puts (the facility's mesh), and again once
    either router is killed and started anew: each keeps trying to reach the other."""
    endpoints = [loopback_endpoint(), loopback_endpoint()]

    def start(mine: int) -> subprocess.Popen[str]:
        command = [sys.executable, "-m", "focustrack_core.wire.router"]
        listen, connect = endpoints[mine], endpoints[1 - mine]
        return subprocess.Popen(
            [*command, "--listen", listen, "--connect", connect], stderr=subprocess.PIPE, text=True
        )

    routers = [start(0), start(1)]
    try:
        received = threading.Event()
        with (
            open_session(connect=[endpoints[0]]) as subscriber,
            open_session(connect=[endpoints[1]]) as pub,
        ):
            subscriber.declare_subscriber("test/mesh", lambda sample: received.set())
            for killed in (None, 0, 1):
                if killed is not None:
                    routers[killed].kill()
                    routers[killed].wait(timeout=10)
                    received.clear()
                    routers[killed] = start(killed)
                for _ in range(200):  # until the subscription has crossed both routers
                    pub.put("test/mesh", b"hello")
                    if received.wait(0.1):
                        break
                assert received.is_set(), f"nothing routed after killing router {killed}"
    finally:
        for router in routers:
            router.kill()
            router.wait(timeout=10)
