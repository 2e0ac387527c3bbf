"""The estimator's Prometheus metrics (prometheus-client), exposed at /metrics.

Each app has a registry of its own (tests run many apps in one process). Counters and
histograms are updated from the event loop and from worker threads (prometheus-client's
are thread-safe); gauges are read when the metrics are scraped.
"""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
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


class EstimatorMetrics:
    """What the estimator exposes at /metrics; the gauges' values are read at each scrape."""

    def __init__(
        self,
        count_slides: Callable[[], float],
        count_live: Callable[[], float],
        strategies_loaded: Callable[[], float],
        store_degraded: Callable[[], float],
    ) -> None:
        prefix = "focustrack_estimator"
        self.registry = CollectorRegistry()
        registry = self.registry
        self.requests = Counter(
            f"{prefix}_requests_total",
            "HTTP requests by route and status",
            ["method", "route", "status"],
            registry=registry,
        )
        self.latency = Histogram(
            f"{prefix}_request_duration_seconds",
            "HTTP request latency by route",
            ["route"],
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        )
        self.filter = Histogram(
            f"{prefix}_filter_duration_seconds",
            "Time spent in strategy calls (planning and taking measurements)",
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        )
        self.measurements = Counter(
            f"{prefix}_measurements_total", "Best-focus measurements recorded", registry=registry
        )
        self.rejections = Counter(
            f"{prefix}_rejections_total",
            "Measurements not used as observations (edge peak, flat curve, gated out)",
            registry=registry,
        )
        self.snapshots_discarded = Counter(
            f"{prefix}_snapshots_discarded_total",
            "Snapshots not used (checksum, contents or the log disagree): the slide was "
            "rebuilt from its log",
            registry=registry,
        )
        gauges = {
            "slides": ("Slides in the store", count_slides),
            "live_slides": ("Slides held in memory", count_live),
            "strategies_loaded": (
                "1 once the strategies are imported (until then the first slide waits for them)",
                strategies_loaded,
            ),
            "store_degraded": (
                "1 while the store is degraded (its disk full, its checkpoints failing, "
                "its database unreachable)",
                store_degraded,
            ),
        }
        for name, (help_text, read) in gauges.items():
            Gauge(f"{prefix}_{name}", help_text, registry=registry).set_function(read)

    def render(self) -> str:
        """The text exposition of every metric."""
        return generate_latest(self.registry).decode()
