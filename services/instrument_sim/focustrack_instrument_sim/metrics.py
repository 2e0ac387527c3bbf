"""The instrument's Prometheus metrics (prometheus-client), served with ``--metrics-port``.

The instrument answers on Zenoh and has no HTTP server of its own: its registry is served by
prometheus-client's (`focustrack_core.http_metrics.metrics_server`). Counted: the stacks
acquired and their frames, the acquisitions refused BUSY (the stage's queue was full) and
those answered with an error, by its code; timed: each acquisition, from the stage taking it
to its reply (every frame published); read at each scrape: the acquisitions waiting.
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh
from prometheus_client import Counter, Gauge, Histogram

from focustrack_core.http_metrics import RegistryMetrics
from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import rpc

#: Latency buckets of an acquisition, seconds: a few frames of a small camera to a wide
#: stack of large frames at the simulated pace.
ACQUISITION_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

Acquire = Callable[[zenoh.Query], instrument_pb2.AcquireReply]


class InstrumentMetrics(RegistryMetrics):
    """`focustrack_instrument_*` in a registry of its own (tests run many instruments in one
    process); `waiting()` gives the acquisitions queued for the stage."""

    def __init__(self, waiting: Callable[[], float]) -> None:
        super().__init__()
        prefix = "focustrack_instrument"
        self.acquisitions = Counter(
            f"{prefix}_acquisitions_total", "Stacks acquired and published", registry=self.registry
        )
        self.frames = Counter(
            f"{prefix}_frames_total", "Frames acquired and published", registry=self.registry
        )
        self.busy = Counter(
            f"{prefix}_busy_total",
            "Acquisitions refused BUSY: the queue for the stage was full",
            registry=self.registry,
        )
        self.errors = Counter(
            f"{prefix}_errors_total",
            "Acquisitions answered with an error (a refusal, a device's failure), by code",
            ["code"],
            registry=self.registry,
        )
        self.latency = Histogram(
            f"{prefix}_acquisition_duration_seconds",
            "From the stage taking an acquisition to its reply, every frame published",
            buckets=ACQUISITION_BUCKETS_S,
            registry=self.registry,
        )
        Gauge(
            f"{prefix}_queued", "Acquisitions waiting for the stage", registry=self.registry
        ).set_function(waiting)

    def observed(self, acquire: Acquire) -> Acquire:
        """`acquire`, timed, its stacks and frames counted, and its error replies by code."""

        def observed_acquire(query: zenoh.Query) -> instrument_pb2.AcquireReply:
            with self.latency.time():
                try:
                    reply = acquire(query)
                except Exception as failure:  # as `rpc.serve` answers it: its code, or INTERNAL
                    code = (
                        failure.error.code
                        if isinstance(failure, rpc.RequestError)
                        else rpc.ErrorCode.ERROR_CODE_INTERNAL
                    )
                    self.errors.labels(common_pb2.ErrorCode.Name(code)).inc()
                    raise
            self.acquisitions.inc()
            self.frames.inc(len(reply.header.z_um))
            return reply

        return observed_acquire
