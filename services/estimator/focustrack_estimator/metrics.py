"""Prometheus text exposition (format 0.0.4) of the estimator's counters and latencies.

Small enough to write by hand (no client library to install): counters and
histograms with labels, rendered on demand. Updated from the event loop and
from worker threads, so every update takes a lock (a few hundred ns).
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable

Labels = tuple[tuple[str, str], ...]

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


def _labels(labels: Labels, extra: Labels = ()) -> str:
    pairs = labels + extra
    if not pairs:
        return ""
    escaped = (
        (k, v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")) for k, v in pairs
    )
    return "{" + ",".join(f'{k}="{v}"' for k, v in escaped) + "}"


def _number(value: float) -> str:
    return "+Inf" if value == math.inf else repr(float(value))


class Counter:
    def __init__(self, name: str, help_text: str) -> None:
        self.name, self.help = name, help_text
        self._values: dict[Labels, float] = {}
        self._lock = threading.Lock()

    def inc(self, amount: float = 1.0, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._values[key] = self._values.get(key, 0.0) + amount

    def render(self) -> list[str]:
        with self._lock:
            values = dict(self._values) or {(): 0.0}
        lines = [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} counter"]
        lines += [f"{self.name}{_labels(k)} {_number(v)}" for k, v in sorted(values.items())]
        return lines


class Histogram:
    def __init__(
        self, name: str, help_text: str, buckets: tuple[float, ...] = LATENCY_BUCKETS_S
    ) -> None:
        self.name, self.help, self.buckets = name, help_text, buckets
        self._series: dict[Labels, tuple[list[int], list[float]]] = {}  # counts, [sum]
        self._lock = threading.Lock()

    def observe(self, value: float, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            counts, total = self._series.setdefault(key, ([0] * (len(self.buckets) + 1), [0.0]))
            counts[bisect.bisect_left(self.buckets, value)] += 1
            total[0] += value

    def render(self) -> list[str]:
        with self._lock:
            series = {k: (list(c), t[0]) for k, (c, t) in self._series.items()}
        lines = [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} histogram"]
        for key, (counts, total) in sorted(series.items()):
            cumulative = 0
            for bound, count in zip((*self.buckets, math.inf), counts, strict=True):
                cumulative += count
                lines.append(
                    f"{self.name}_bucket{_labels(key, (('le', _number(bound)),))} {cumulative}"
                )
            lines.append(f"{self.name}_sum{_labels(key)} {_number(total)}")
            lines.append(f"{self.name}_count{_labels(key)} {cumulative}")
        return lines


class Gauge:
    """A value read when the metrics are scraped."""

    def __init__(self, name: str, help_text: str, read: Callable[[], float]) -> None:
        self.name, self.help, self.read = name, help_text, read

    def render(self) -> list[str]:
        return [
            f"# HELP {self.name} {self.help}",
            f"# TYPE {self.name} gauge",
            f"{self.name} {_number(self.read())}",
        ]


class EstimatorMetrics:
    """What the estimator exposes at /metrics."""

    def __init__(
        self,
        count_slides: Callable[[], float],
        count_live: Callable[[], float],
        strategies_loaded: Callable[[], float],
        store_degraded: Callable[[], float],
    ) -> None:
        prefix = "focustrack_estimator"
        self.requests = Counter(f"{prefix}_requests_total", "HTTP requests by route and status")
        self.latency = Histogram(
            f"{prefix}_request_duration_seconds", "HTTP request latency by route"
        )
        self.filter = Histogram(
            f"{prefix}_filter_duration_seconds",
            "Time spent in strategy calls (planning and taking measurements)",
        )
        self.measurements = Counter(
            f"{prefix}_measurements_total", "Best-focus measurements recorded"
        )
        self.rejections = Counter(
            f"{prefix}_rejections_total",
            "Measurements not used as observations (edge peak, flat curve, gated out)",
        )
        self.snapshots_discarded = Counter(
            f"{prefix}_snapshots_discarded_total",
            "Snapshots not used (checksum, contents or the log disagree): the slide was "
            "rebuilt from its log",
        )
        self._gauges = (
            Gauge(f"{prefix}_slides", "Slides in the store", count_slides),
            Gauge(f"{prefix}_live_slides", "Slides held in memory", count_live),
            Gauge(
                f"{prefix}_strategies_loaded",
                "1 once the strategies are imported (until then the first slide waits for them)",
                strategies_loaded,
            ),
            Gauge(
                f"{prefix}_store_degraded",
                "1 while the store is degraded (its disk full, its checkpoints failing, "
                "its database unreachable)",
                store_degraded,
            ),
        )

    def render(self) -> str:
        metrics = (
            self.requests,
            self.latency,
            self.filter,
            self.measurements,
            self.rejections,
            self.snapshots_discarded,
            *self._gauges,
        )
        return "\n".join(line for metric in metrics for line in metric.render()) + "\n"
