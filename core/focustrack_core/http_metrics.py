"""A service's Prometheus metrics (prometheus-client, extra `metrics`): its HTTP requests
counted and timed by route, in a registry of the service's own, rendered for /metrics.

Each app has a registry of its own (tests run many apps in one process). The counters
and histograms are thread-safe: updated from the event loop and from worker threads.
`focustrack_core.serving.RequestTimer` feeds `observe_request`. A service without an HTTP
server of its own (the instrument, a scan) serves its registry on a port of its own instead
(`MetricsPortSettings`, `metrics_server`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import ClassVar

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.exposition import start_http_server
from prometheus_client.metrics import disable_created_metrics
from pydantic import Field

from focustrack_core.serving import ListenError, http_url
from focustrack_core.settings import ServiceSettings

log = logging.getLogger(__name__)

# A `_created` series beside every counter doubles the text and no dashboard reads it.
disable_created_metrics()

#: Latency buckets in seconds: 0.1 ms to 2.5 s.
LATENCY_BUCKETS_S = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
)

#: The media type of the text exposition.
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class RegistryMetrics:
    """Metrics in a registry of their own, rendered as Prometheus text; subclasses add them."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()

    def render(self) -> str:
        """The text exposition of every metric of the registry."""
        return generate_latest(self.registry).decode()


class HttpMetrics(RegistryMetrics):
    """`{prefix}_requests_total` (method, route, status) and
    `{prefix}_request_duration_seconds` (route), in `registry`; a service adds its own."""

    def __init__(self, prefix: str) -> None:
        super().__init__()
        self.prefix = prefix
        self.requests = Counter(
            f"{prefix}_requests_total",
            "HTTP requests by route and status",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            f"{prefix}_request_duration_seconds",
            "HTTP request latency by route",
            ["route"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        """Count and time one HTTP request (`focustrack_core.serving.RequestTimer`)."""
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(route).observe(seconds)


class MetricsPortSettings(ServiceSettings):
    """The options of a service that serves its metrics on a port of its own (off unless
    `metrics_port` is set)."""

    help_heading: ClassVar[str | None] = "metrics"

    metrics_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="serve Prometheus metrics at http://--metrics-host:PORT/metrics (0: any "
        "free port; unset: not served)",
    )
    metrics_host: str = Field(
        "127.0.0.1",
        min_length=1,
        description="the address the metrics listen on (0.0.0.0: every interface, for a "
        "Prometheus elsewhere)",
    )


@contextmanager
def metrics_server(
    registry: CollectorRegistry, host: str, port: int | None
) -> Iterator[str | None]:
    """`registry` served as Prometheus text on http://`host`:`port`/metrics (by
    prometheus-client's own server, on a thread) while the block runs; yields its URL, or
    None without a `port` (nothing served)."""
    if port is None:
        yield None
        return
    try:
        server, thread = start_http_server(port, host, registry)
    except OSError as error:
        raise ListenError.of("metrics", host, port, error) from error
    url = http_url(host, server.server_port, "/metrics")
    log.info("metrics at %s", url)
    try:
        yield url
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
