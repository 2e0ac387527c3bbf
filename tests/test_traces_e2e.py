"""Traces of each tile across the services, end to end on loopback: a Zenoh router (this
process), the instrument, focus and estimator services and `focustrack scan`, each a real
process, exporting over OTLP/HTTP to a small collector of the test's own; and, with tracing
off, no trace context on the wire and nothing exported. The instrument's metrics port too."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import pytest
import zenoh
from opentelemetry.proto.collector.trace.v1.trace_service_pb2 import (
    ExportTraceServiceRequest,
    ExportTraceServiceResponse,
)
from opentelemetry.proto.trace.v1.trace_pb2 import Span

from focustrack.local_stack import INSTRUMENT, LocalStack
from focustrack_core.tracing import OTLP_VARIABLES, TRACES_PATH
from focustrack_core.v1 import focus_pb2
from focustrack_core.wire import codec, keys
from focustrack_core.wire.session import free_port

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

ROWS = COLS = 3
SLIDE = "slide-0"
ACQUIRE_QUERY = f"query {keys.acquire_key(INSTRUMENT)}"
MEASUREMENT_ROUTE = "POST /v1/slides/{slide_id}/measurements"


@dataclass(frozen=True)
class Received:
    """A span as a collector got it, with the name of the service that sent it."""

    service: str
    span: Span

    @property
    def attributes(self) -> dict[str, object]:
        return {
            item.key: getattr(item.value, item.value.WhichOneof("value"))
            for item in self.span.attributes
        }


class Collector(ThreadingHTTPServer):
    """An OTLP/HTTP trace collector on loopback that keeps every span it is sent."""

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _CollectorHandler)
        self.received: list[Received] = []
        self.lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_port}"

    def spans(self) -> list[Received]:
        with self.lock:
            return list(self.received)


class _CollectorHandler(BaseHTTPRequestHandler):
    server: Collector

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        assert self.path == TRACES_PATH, self.path
        request = ExportTraceServiceRequest.FromString(body)
        with self.server.lock:
            for resource_spans in request.resource_spans:
                service = next(
                    item.value.string_value
                    for item in resource_spans.resource.attributes
                    if item.key == "service.name"
                )
                for scope in resource_spans.scope_spans:
                    self.server.received += [Received(service, span) for span in scope.spans]
        reply = ExportTraceServiceResponse().SerializeToString()
        self.send_response(200)
        self.send_header("Content-Type", "application/x-protobuf")
        self.send_header("Content-Length", str(len(reply)))
        self.end_headers()
        self.wfile.write(reply)

    def log_message(self, *_: object) -> None:  # quiet
        pass


@contextmanager
def collector() -> Iterator[Collector]:
    server = Collector()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


@contextmanager
def stack_of(work_dir: Path, *instrument_args: str) -> Iterator[LocalStack]:
    args = ["--seed", "5", "--slides", "1", "--rows", str(ROWS), "--cols", str(COLS)]
    args += ["--width", "128", "--height", "128", *instrument_args]
    with LocalStack(work_dir, args) as stack:
        yield stack


def scan(stack: LocalStack, out_dir: Path, *extra: str) -> None:
    command = [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack.estimator_url, "--connect", stack.endpoint,
        "--instrument", INSTRUMENT, "--slide", SLIDE, "--out", str(out_dir), *extra,
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, env=os.environ)
    assert done.returncode == 0, done.stderr
    assert f"{ROWS * COLS} tiles" in done.stdout


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    deadline_s = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline_s, f"no {what} within {timeout_s:g} s"
        time.sleep(0.1)


def by_trace(spans: list[Received]) -> dict[bytes, list[Received]]:
    traces: dict[bytes, list[Received]] = defaultdict(list)
    for received in spans:
        traces[received.span.trace_id].append(received)
    return traces


def complete(trace: list[Received]) -> bool:
    """A tile's trace with the spans of all four services."""
    return {"focustrack-scheduler", "focustrack-instrument", "focustrack-focus"} <= {
        received.service for received in trace
    } and any(received.span.name == MEASUREMENT_ROUTE for received in trace)


def one(trace: list[Received], service: str, name: str, parent: Span) -> Span:
    """The span `name` of `service` in `trace` whose parent is `parent` (the first, by start)."""
    found = sorted(
        (
            received.span
            for received in trace
            if (received.service, received.span.name) == (service, name)
            and received.span.parent_span_id == parent.span_id
        ),
        key=lambda span: span.start_time_unix_nano,
    )
    assert found, f"no span {name!r} of {service} under {parent.name!r}"
    return found[0]


def test_each_tile_is_one_trace_across_scheduler_instrument_focus_and_estimator(
    http: httpx.Client, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    metrics_port = free_port()
    for name in OTLP_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    with collector() as otlp:
        # The services find the collector as deployments tell them: the standard variable
        # (the scan is told by its option, below); their batches go out every 0.1 s.
        monkeypatch.setenv("OTEL_EXPORTER_OTLP_ENDPOINT", otlp.url)
        monkeypatch.setenv("OTEL_BSP_SCHEDULE_DELAY", "100")
        with stack_of(tmp_path / "stack", "--metrics-port", str(metrics_port)) as stack:
            monkeypatch.delenv("OTEL_EXPORTER_OTLP_ENDPOINT")
            scan(stack, tmp_path / "scan", "--otlp-endpoint", otlp.url)
            instrument_metrics = http.get(f"http://127.0.0.1:{metrics_port}/metrics").text

            def every_tile_traced() -> bool:
                traces = by_trace(otlp.spans()).values()
                return sum(complete(trace) for trace in traces) >= ROWS * COLS

            wait_for(every_tile_traced, "trace of every tile with the spans of each service")
        spans = otlp.spans()  # and those the services sent as they stopped

    traces = by_trace(spans)
    roots = [
        (trace_id, received)
        for trace_id, trace in traces.items()
        for received in trace
        if received.span.name == "tile"
    ]
    tiles = {(root.attributes["row"], root.attributes["col"]) for _, root in roots}
    assert tiles == {(row, col) for row in range(ROWS) for col in range(COLS)}
    for trace_id, root in roots:
        trace = traces[trace_id]
        if not complete(trace):
            continue  # a revisit, or a laser reading: not every service has a part in it
        assert root.service == "focustrack-scheduler" and root.span.parent_span_id == b""
        assert root.attributes["slide"] == SLIDE
        assert sum(received.span.name == "tile" for received in trace) == 1  # one tile, one trace
        # scheduler -> instrument -> focus service, through the query and the stack's header
        query = one(trace, "focustrack-scheduler", ACQUIRE_QUERY, root.span)
        assert query.kind == Span.SPAN_KIND_CLIENT
        acquisition = one(trace, "focustrack-instrument", ACQUIRE_QUERY, query)
        assert acquisition.kind == Span.SPAN_KIND_SERVER
        analysis = one(trace, "focustrack-focus", "focus stack", acquisition)
        assert analysis.kind == Span.SPAN_KIND_CONSUMER
        # scheduler -> estimator, over HTTP
        post = one(trace, "focustrack-scheduler", MEASUREMENT_ROUTE, root.span)
        served = one(trace, "focustrack-estimator", MEASUREMENT_ROUTE, post)
        assert served.kind == Span.SPAN_KIND_SERVER
        assert root.span.start_time_unix_nano <= query.start_time_unix_nano
        # the focus service reads frames as they stream: its span may end before the
        # instrument's reply is sent, but it cannot start before the acquisition did
        assert acquisition.start_time_unix_nano <= analysis.start_time_unix_nano
    # no span lost: every span's parent is in its trace (a root: a tile, or a request the
    # scheduler made before the first tile, such as the slide's creation)
    for trace in traces.values():
        ids = {received.span.span_id for received in trace}
        for received in trace:
            assert received.span.parent_span_id in ids | {b""}, received.span.name

    lines = instrument_metrics.splitlines()
    acquired = next(line for line in lines if line.startswith("focustrack_instrument_acquisitions"))
    n_acquired = float(acquired.split()[-1])
    answered = [
        r for r in spans if (r.service, r.span.name) == ("focustrack-instrument", ACQUIRE_QUERY)
    ]
    assert n_acquired == len(answered) >= ROWS * COLS
    assert any(line.startswith("focustrack_instrument_frames_total ") for line in lines)


def test_with_tracing_off_no_trace_context_travels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in OTLP_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    with stack_of(tmp_path / "stack") as stack:
        assert stack.session is not None
        sent: list[str] = []  # the trace context of every frame and focus result

        def frame_trace(sample: zenoh.Sample) -> None:
            assert sample.attachment is not None
            sent.append(codec.zframe_header(sample.attachment.to_bytes()).stack.trace.traceparent)

        def result_trace(sample: zenoh.Sample) -> None:
            result = focus_pb2.FocusResult.FromString(codec.payload_bytes(sample.payload))
            sent.append(result.trace.traceparent)

        frames = stack.session.declare_subscriber(keys.zframe_pattern(SLIDE), frame_trace)
        results = stack.session.declare_subscriber(keys.focus_pattern(SLIDE), result_trace)
        scan(stack, tmp_path / "scan")
        frames.undeclare()
        results.undeclare()
    assert len(sent) > ROWS * COLS and set(sent) == {""}
