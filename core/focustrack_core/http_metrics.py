"""A service's Prometheus metrics (prometheus-client, extra `metrics`): its HTTP requests
counted and timed by route, in a registry of the service's own, rendered for /metrics.

Each app has a registry of its own (tests run many apps in one process). The counters
and histograms are thread-safe: updated from the event loop and from worker threads.
`focustrack_core.serving.RequestTimer` feeds `observe_request`.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.metrics import disable_created_metrics

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


class HttpMetrics:
    """`{prefix}_requests_total` (method, route, status) and
    `{prefix}_request_duration_seconds` (route), in `registry`; a service adds its own."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.registry = CollectorRegistry()
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

    def render(self) -> str:
        """The text exposition of every metric of the registry."""
        return generate_latest(self.registry).decode()
