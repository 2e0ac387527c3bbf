"""A service's metrics on a port of their own (`metrics_server`): the instrument and a scan,
which have no HTTP server of their own, serve their registry so."""

from __future__ import annotations

import httpx
import pytest
from prometheus_client import Counter

from focustrack_core.http_metrics import RegistryMetrics, metrics_server


def test_metrics_are_served_on_a_port_of_their_own_only_when_asked() -> None:
    metrics = RegistryMetrics()
    Counter("focustrack_test_things_total", "Things", registry=metrics.registry).inc(3)
    with metrics_server(metrics.registry, "127.0.0.1", None) as url:
        assert url is None
    with metrics_server(metrics.registry, "127.0.0.1", 0) as url:
        assert url is not None
        assert "focustrack_test_things_total 3.0" in httpx.get(url).text.splitlines()
    with pytest.raises(httpx.TransportError):
        httpx.get(url)
