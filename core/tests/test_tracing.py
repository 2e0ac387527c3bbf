"""The trace context on every hop (`focustrack_core.tracing`): its wire form, a Zenoh query's
attachment between real sessions, an HTTP request's headers into a real uvicorn server, and
tracing off unless an endpoint is named. These run without an OpenTelemetry SDK (a process
that is not traced): the trace a caller is in still passes through, no span is recorded; the
spans themselves are checked end to end (tests/test_traces_e2e.py)."""

from __future__ import annotations

import httpx
import pytest
import zenoh
from fastapi import FastAPI
from opentelemetry import trace
from opentelemetry.trace import NonRecordingSpan, SpanContext, TraceFlags

from focustrack_core import tracing
from focustrack_core.serving import BackgroundServer
from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import rpc

TRACE_ID = 0x4BF92F3577B34DA6A3CE929D0E0E4736
SPAN_ID = 0x00F067AA0BA902B7
TRACEPARENT = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01"
KEY = "focustrack/v1/instrument/test/acquire"


def _caller_span() -> NonRecordingSpan:
    """The span of a caller in a trace (from another process, say)."""
    return NonRecordingSpan(
        SpanContext(TRACE_ID, SPAN_ID, is_remote=False, trace_flags=TraceFlags(1))
    )


def _current_traceparent() -> str:
    wire = tracing.to_wire()
    return "" if wire is None else wire.traceparent


def test_the_wire_form_is_w3c_traceparent_both_ways() -> None:
    context = trace.set_span_in_context(_caller_span())
    wire = tracing.to_wire(context)
    assert wire is not None and wire.traceparent == TRACEPARENT
    back = tracing.from_wire(common_pb2.TraceContext.FromString(wire.SerializeToString()))
    assert back is not None
    assert trace.get_current_span(back).get_span_context().trace_id == TRACE_ID
    assert tracing.to_wire() is None  # outside any trace: nothing to send
    assert tracing.from_wire(None) is None
    assert tracing.from_wire(common_pb2.TraceContext(traceparent="00-zz-11-01")) is None
    assert tracing.of_attachment(None) is None
    assert tracing.of_attachment(b"\xff\xff\xff") is None  # not a TraceContext: ignored


def test_a_span_joins_only_a_trace_that_comes_in() -> None:
    with tracing.joined("work", None, trace.SpanKind.SERVER) as span:
        assert not span.get_span_context().is_valid and _current_traceparent() == ""
    parent = common_pb2.TraceContext(traceparent=TRACEPARENT)
    with tracing.joined("work", parent, trace.SpanKind.SERVER):
        assert _current_traceparent().split("-")[1] == f"{TRACE_ID:032x}"


def test_a_query_carries_the_callers_trace_to_the_queryable(
    pair: tuple[zenoh.Session, zenoh.Session, zenoh.Session],
) -> None:
    hub, caller, _ = pair
    seen: list[tuple[bool, str]] = []

    def handle(query: zenoh.Query) -> instrument_pb2.AcquireReply:
        seen.append((query.attachment is not None, _current_traceparent()))
        return instrument_pb2.AcquireReply()

    with rpc.declare_answering(hub, KEY, handle):
        request = instrument_pb2.AcquireRequest(slide="s")
        rpc.call(caller, KEY, request, instrument_pb2.AcquireReply)
        with trace.use_span(_caller_span()):
            rpc.call(caller, KEY, request, instrument_pb2.AcquireReply)
    assert seen[0] == (False, "")  # outside a trace: no attachment, no span
    attached, traceparent = seen[1]
    assert attached and traceparent.split("-")[1] == f"{TRACE_ID:032x}"


def test_an_http_request_carries_the_callers_trace_into_the_served_route(
    http: httpx.Client,
) -> None:
    app = FastAPI()

    @app.get("/where")
    def where() -> dict[str, str]:
        return {"traceparent": _current_traceparent()}

    app.add_middleware(tracing.TraceRequests)
    with BackgroundServer(app) as server:
        url = server.url + "where"
        assert http.get(url).json() == {"traceparent": ""}
        joined = http.get(url, headers={"traceparent": TRACEPARENT}).json()["traceparent"]
    assert joined.split("-")[1] == f"{TRACE_ID:032x}"


def test_tracing_is_off_unless_an_endpoint_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in tracing.OTLP_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert tracing.configure("test") is False
    assert isinstance(trace.get_tracer_provider(), trace.ProxyTracerProvider)  # nothing set
    with pytest.raises(ValueError, match="otlp_endpoint"):
        tracing.TracingSettings(otlp_endpoint="127.0.0.1:4318")  # a URL, with its scheme
