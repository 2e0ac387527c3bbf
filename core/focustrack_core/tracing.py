"""Traces of each tile across the services (OpenTelemetry), off unless a service is told where
to send them.

A service calls `configure(service_name, endpoint)` once, at its start. With an OTLP
endpoint (its ``--otlp-endpoint``, or the standard ``OTEL_EXPORTER_OTLP_ENDPOINT`` or
``OTEL_EXPORTER_OTLP_TRACES_ENDPOINT``) its spans are batched and exported over OTLP/HTTP;
without one nothing is set up: the OpenTelemetry API's tracer is a no-op that draws no ids
and records nothing, so no trace context is sent either.

The W3C trace context (``traceparent``, ``tracestate``) goes with every hop of a tile:
- HTTP: the client library (`focustrack_client`) sends the caller's span in headers;
  `TraceRequests` (ASGI) serves such a request in a server span, a child of the caller's.
- Zenoh queries: `query_span` is a client span whose context `rpc.call` attaches to the
  query (a `TraceContext`, serialised); the queryable answers inside `joined`, a server span
  whose parent is that context (`focustrack_core.wire.rpc`).
- Zenoh headers: the instrument writes its span of an acquisition into the stack's header
  (`to_wire`), so every frame carries it; the focus service's span of the stack is its
  child and goes, in turn, into the FocusResult.

The services' spans join a trace, they never start one (the scheduler starts one per
tile): a request, a query or a stack without a trace context is answered without a span, so
health probes, scrapes and info queries make no traces.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import ClassVar

from google.protobuf.message import DecodeError
from opentelemetry import propagate, trace
from opentelemetry.context import Context
from opentelemetry.trace import INVALID_SPAN, Span, SpanKind, StatusCode
from opentelemetry.trace.propagation.tracecontext import TraceContextTextMapPropagator
from pydantic import Field

from focustrack_core.serving import ASGIApp, Receive, RequestTimer, Scope, Send
from focustrack_core.settings import ServiceSettings
from focustrack_core.v1 import common_pb2

#: The instrumentation scope of every span of FocusTrack.
TRACER_NAME = "focustrack"

#: The standard variables that name an OTLP endpoint: either turns tracing on.
OTLP_VARIABLES = ("OTEL_EXPORTER_OTLP_ENDPOINT", "OTEL_EXPORTER_OTLP_TRACES_ENDPOINT")

#: Where an OTLP/HTTP collector takes spans, under its base URL (as the standard variable).
TRACES_PATH = "/v1/traces"

# The wire's TraceContext is W3C's, whatever propagators the process uses over HTTP.
_W3C = TraceContextTextMapPropagator()


class TracingSettings(ServiceSettings):
    """The tracing option a service adds to its settings (`configure` reads it)."""

    help_heading: ClassVar[str | None] = "tracing"

    otlp_endpoint: str | None = Field(
        None,
        pattern=r"^https?://",
        description="export traces over OTLP/HTTP to this collector's base URL, e.g. "
        "http://127.0.0.1:4318 (spans go to its /v1/traces); unset: where "
        "OTEL_EXPORTER_OTLP_ENDPOINT says, and without it no tracing",
    )


def tracer() -> trace.Tracer:
    """FocusTrack's tracer (a no-op until `configure` sets a provider)."""
    return trace.get_tracer(TRACER_NAME)


def configure(service_name: str, endpoint: str | None = None) -> bool:
    """Export this process's spans, as `service_name`, over OTLP/HTTP to `endpoint` (a
    collector's base URL) or where the standard variables say; False, and nothing set up,
    when neither names one. Call it once per process, at its start."""
    if endpoint is None and not any(os.environ.get(name) for name in OTLP_VARIABLES):
        return False
    # Only a traced process pays for the SDK's import (about 0.2 s).
    from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter
    from opentelemetry.sdk.resources import SERVICE_NAME, Resource
    from opentelemetry.sdk.trace import TracerProvider
    from opentelemetry.sdk.trace.export import BatchSpanProcessor

    url = None if endpoint is None else endpoint.rstrip("/") + TRACES_PATH
    # The provider flushes its batch at exit (shutdown_on_exit): a stopped service's last
    # spans are sent.
    provider = TracerProvider(resource=Resource.create({SERVICE_NAME: service_name}))
    provider.add_span_processor(BatchSpanProcessor(OTLPSpanExporter(endpoint=url)))
    trace.set_tracer_provider(provider)
    return True


def to_wire(context: Context | None = None) -> common_pb2.TraceContext | None:
    """The W3C trace context of the current span (or of `context`'s), None where there is
    no valid span (not tracing)."""
    carrier: dict[str, str] = {}
    _W3C.inject(carrier, context)
    if "traceparent" not in carrier:
        return None
    return common_pb2.TraceContext(
        traceparent=carrier["traceparent"], tracestate=carrier.get("tracestate", "")
    )


def from_wire(message: common_pb2.TraceContext | None) -> Context | None:
    """The context whose span `message` names; None where it names none (absent, or not a
    valid traceparent)."""
    if message is None or not message.traceparent:
        return None
    carrier = {"traceparent": message.traceparent}
    if message.tracestate:
        carrier["tracestate"] = message.tracestate
    context = _W3C.extract(carrier)
    return context if trace.get_current_span(context).get_span_context().is_valid else None


def attachment() -> bytes | None:
    """A query's attachment: the current span's `TraceContext`, serialised (None: no span)."""
    message = to_wire()
    return None if message is None else message.SerializeToString()


def of_attachment(data: bytes | None) -> common_pb2.TraceContext | None:
    """The `TraceContext` of a query's attachment; None for none or one that is not one."""
    if not data:
        return None
    try:
        return common_pb2.TraceContext.FromString(data)
    except DecodeError:
        return None


def joined(
    name: str,
    parent: common_pb2.TraceContext | None,
    kind: SpanKind,
    **attributes: str | int | float,
) -> AbstractContextManager[Span]:
    """The current span `name` within the trace of `parent` (its child), with `attributes`,
    while the block runs; where `parent` names no span, no span at all (an invalid one, on
    which every call is a no-op)."""
    context = from_wire(parent)
    if context is None:
        return nullcontext(INVALID_SPAN)
    return tracer().start_as_current_span(name, context, kind, attributes)


@contextmanager
def query_span(key_expr: str) -> Iterator[bytes | None]:
    """A client span of a query on `key_expr` while the block runs, a child of the current
    span; yields the attachment that carries it (None, and no span, outside any trace)."""
    if not trace.get_current_span().get_span_context().is_valid:
        yield None
        return
    with tracer().start_as_current_span(f"query {key_expr}", kind=SpanKind.CLIENT):
        yield attachment()


def fail(span: Span, why: str) -> None:
    """Mark `span` failed, saying why (a no-op on a span that is not recorded)."""
    span.set_status(StatusCode.ERROR, why)


class TraceRequests:
    """ASGI middleware: an HTTP request whose headers carry a trace context (``traceparent``)
    is served in a server span, a child of the caller's, named by its method and route
    template (``POST /v1/slides/{slide_id}/measurements``), with the status sent (a 5xx fails
    it); a request without one (a probe, a scrape, a caller that does not trace) in none."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = RequestTimer(app, _describe_request)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {
            name.decode("latin-1"): value.decode("latin-1") for name, value in scope["headers"]
        }
        parent = propagate.extract(headers)
        if not trace.get_current_span(parent).get_span_context().is_valid:
            await self.app(scope, receive, send)
            return
        with tracer().start_as_current_span(scope["method"], parent, SpanKind.SERVER):
            await self.app(scope, receive, send)


def _describe_request(method: str, route: str, status: int, _seconds: float) -> None:
    """Name the current (server) span after the request's route, and give its status."""
    span = trace.get_current_span()
    if not span.is_recording():
        return
    span.update_name(f"{method} {route}")
    span.set_attributes({"http.route": route, "http.response.status_code": status})
    if status >= 500:
        fail(span, f"HTTP {status}")
