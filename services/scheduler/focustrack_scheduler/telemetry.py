"""What a scan tells an operator while it runs: Prometheus metrics and a trace of each tile.

`ScanMetrics` (`focustrack_scan_*`, prometheus-client, a registry of the scan's own): tiles
done (their first image kept; Prometheus' `rate` of it is the tiles per second), stacks and
frames acquired, measurements posted, retries of the instrument and the estimator, faults by
kind, each plan step's latency and each tile's, and whether a scan runs. The live view serves
them at ``GET /metrics``, and ``--metrics-port`` on a port of their own.

`TileSpans` (OpenTelemetry, `focustrack_core.tracing`): one root span per tile, ``tile``,
from the first step that names the tile to the first that names another (or the scan's end);
each step runs inside it, so the instrument's query, the estimator's requests and, through
the stack's header, the focus service's analysis join the tile's trace. A step that names
no tile (asking the estimator what comes next) stays in the tile before it.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from opentelemetry import trace
from opentelemetry.context import Context
from prometheus_client import Counter, Gauge, Histogram

from focustrack_core.http_metrics import LATENCY_BUCKETS_S, RegistryMetrics
from focustrack_core.tracing import tracer
from focustrack_scheduler.plan import (
    Acquire,
    AcquirePhase,
    AwaitFocus,
    KeepPlanes,
    KeepTile,
    PostMeasurement,
    ReadLaser,
    Step,
)

#: Latency buckets of a plan step and of a tile, seconds: from a quick request to the wait
#: for a slow stack's focus.
STEP_BUCKETS_S = (*LATENCY_BUCKETS_S, 5.0, 10.0, 30.0, 60.0)

#: The faults a scan counts (`ScanMetrics.faults`), each a label value.
FAULTS = (
    "focus_timeout",  # no focus result in time: the stack is acquired again
    "focus_lost",  # the bus went down while it was awaited, and is back: acquired again
    "focus_service_lost",  # the focus service went while it was awaited, one is there
    "phase_service_lost",  # the phase service went while it was awaited: the tile has no phase
    "result_rejected",  # a focus or phase result refused (no tag, another nonce, a copy)
    "frames_gone",  # the instrument no longer held a stack's frames: taken again
)


class ScanMetrics(RegistryMetrics):
    """`focustrack_scan_*` (module docstring); `take` follows the scan's record."""

    def __init__(self) -> None:
        super().__init__()
        prefix, registry = "focustrack_scan", self.registry
        self.running = Gauge(f"{prefix}_running", "1 while a scan runs", registry=registry)
        self.tiles = Gauge(f"{prefix}_tiles", "Tiles of the slide being scanned", registry=registry)
        self.tiles_done = Counter(
            f"{prefix}_tiles_done_total", "Tiles whose image is kept", registry=registry
        )
        self.acquisitions = Counter(
            f"{prefix}_acquisitions_total", "Stacks acquired", registry=registry
        )
        self.frames = Counter(f"{prefix}_frames_total", "Frames acquired", registry=registry)
        self.measurements = Counter(
            f"{prefix}_measurements_total", "Measurements posted", registry=registry
        )
        self.retries = Counter(
            f"{prefix}_retries_total",
            "Calls sent again (no answer, busy, or an estimator's 5xx), by service",
            ["service"],
            registry=registry,
        )
        self.faults = Counter(
            f"{prefix}_faults_total",
            "Faults the scan rode out, by kind: " + ", ".join(FAULTS),
            ["kind"],
            registry=registry,
        )
        self.step_latency = Histogram(
            f"{prefix}_step_duration_seconds",
            "Each step of the scan plan, retries included, by step",
            ["step"],
            buckets=STEP_BUCKETS_S,
            registry=registry,
        )
        self.tile_latency = Histogram(
            f"{prefix}_tile_duration_seconds",
            "Each tile, from its first step to the next tile's",
            buckets=STEP_BUCKETS_S,
            registry=registry,
        )
        for kind in FAULTS:  # every kind from the start: a rate of none is 0, not missing
            self.faults.labels(kind)
        for service in ("instrument", "estimator"):
            self.retries.labels(service)
        self._kept: set[tuple[int, int]] = set()

    def follow(self, kept: Iterable[tuple[int, int]]) -> None:
        """The tiles already kept (a resumed scan): not counted again."""
        self._kept.update(kept)

    def take(self, entry: dict[str, Any]) -> None:
        """Count one entry of the scan's record (`ScanRecord.listeners`)."""
        event = entry["event"]
        if event == "acquired":
            self.acquisitions.inc()
            self.frames.inc(entry["n_frames"])
        elif event == "measured":
            self.measurements.inc()
        elif event == "kept" and (tile := (entry["row"], entry["col"])) not in self._kept:
            self._kept.add(tile)
            self.tiles_done.inc()


def tile_of(step: Step) -> tuple[int, int] | None:
    """The tile (row, col) a step works on; None for one that names none."""
    if isinstance(step, Acquire | AwaitFocus | PostMeasurement | ReadLaser):
        return step.acquisition.row, step.acquisition.col
    if isinstance(step, KeepTile | KeepPlanes | AcquirePhase):
        return step.row, step.col
    return None


class TileSpans:
    """The current tile's span (module docstring), and its latency into `metrics`."""

    def __init__(self, metrics: ScanMetrics) -> None:
        self.metrics = metrics
        self._tile: tuple[int, int] | None = None
        self._span: trace.Span = trace.INVALID_SPAN
        self._started_s = 0.0

    @contextmanager
    def step(self, step: Step, slide: str) -> Iterator[None]:
        """Run `step` in its tile's span (a new one for a new tile of `slide`), timed."""
        tile = tile_of(step)
        if tile is not None and tile != self._tile:
            self.close()
            self._tile, self._started_s = tile, time.perf_counter()
            self._span = tracer().start_span(
                "tile",
                Context(),  # a trace of its own
                attributes={"slide": slide, "row": tile[0], "col": tile[1]},
            )
        with (
            trace.use_span(self._span),
            self.metrics.step_latency.labels(type(step).__name__).time(),
        ):
            yield

    def close(self) -> None:
        """End the current tile's span, if any."""
        if self._tile is not None:
            self._span.end()
            self.metrics.tile_latency.observe(time.perf_counter() - self._started_s)
        self._tile, self._span = None, trace.INVALID_SPAN
