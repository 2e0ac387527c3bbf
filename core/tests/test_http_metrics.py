"""A service's metrics on a port of their own (`metrics_server`): the instrument and a scan,
which have no HTTP server of their own, serve their registry so."""

from __future__ import annotations

import socket

import httpx
import pytest
from prometheus_client import Counter

from focustrack_core.http_metrics import RegistryMetrics, metrics_server
from focustrack_core.serving import BackgroundServer, ListenError, listening_socket


def test_metrics_are_served_on_a_port_of_their_own_only_when_asked(http: httpx.Client) -> None:
    metrics = RegistryMetrics()
    Counter("focustrack_test_things_total", "Things", registry=metrics.registry).inc(3)
    with metrics_server(metrics.registry, "127.0.0.1", None) as url:
        assert url is None
    with metrics_server(metrics.registry, "127.0.0.1", 0) as url:
        assert url is not None
        assert "focustrack_test_things_total 3.0" in http.get(url).text.splitlines()
    with pytest.raises(httpx.TransportError):
        http.get(url)


def test_a_port_in_use_is_a_listen_error_that_names_the_server_and_the_address() -> None:
    """Both the metrics server and a `BackgroundServer` (the scan's live view) bind in the
    caller's thread: a port in use is one error there, not a server thread that died."""

    async def app(scope: dict, receive: object, send: object) -> None:  # never called
        raise AssertionError

    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        with (
            pytest.raises(ListenError, match=rf"metrics server .* 127.0.0.1:{port}: .*in use"),
            metrics_server(RegistryMetrics().registry, "127.0.0.1", port),
        ):
            pass
        with pytest.raises(ListenError, match=rf"live-view server .* 127.0.0.1:{port}: .*in use"):
            BackgroundServer(app, port=port, name="live-view").start()


def test_a_host_that_does_not_resolve_is_said_in_words() -> None:
    """getaddrinfo's errors have negative numbers, which strerror called "Unknown error -2"."""
    with pytest.raises(ListenError, match=r"cannot listen on no-such-host\.invalid:0: 'no-such"):
        listening_socket("no-such-host.invalid", 0, "phase")
