"""The estimator's Prometheus metrics (prometheus-client), exposed at /metrics.

Each app has a registry of its own (tests run many apps in one process). Counters and
histograms are updated from the event loop and from worker threads (prometheus-client's
are thread-safe); gauges are read when the metrics are scraped.
"""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import Counter, Gauge, Histogram

from focustrack_core.http_metrics import LATENCY_BUCKETS_S, HttpMetrics


class EstimatorMetrics(HttpMetrics):
    """What the estimator exposes at /metrics: its HTTP requests, and its own counters and
    gauges (the gauges' values read at each scrape)."""

    def __init__(
        self,
        count_slides: Callable[[], float],
        count_live: Callable[[], float],
        strategies_loaded: Callable[[], float],
        store_degraded: Callable[[], float],
    ) -> None:
        super().__init__("focustrack_estimator")
        prefix, registry = self.prefix, self.registry
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
