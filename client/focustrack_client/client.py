"""Clients of the estimator's REST API: `EstimatorClient` (blocking) and `AsyncEstimatorClient`.

Both speak the same endpoints and return the same typed models
(`focustrack_client.models`); an error reply raises the `EstimatorError`
subclass named by its `code` (`errors.py`), never a bare HTTP error. Use either
as a context manager so its connections are closed::

    with EstimatorClient("http://127.0.0.1:8100", token="...") as estimator:
        slide = estimator.create_slide(SlideCreate(strategy="kf-2d", grid=Grid(rows=20, cols=20)))
        while not (step := estimator.next(slide.id)).done:
            ...  # acquire the stack step.z_low_um .. step.z_high_um, find its best focus
            estimator.measure(slide.id, MeasurementIn(row=step.row, col=step.col,
                                                      sequence=step.sequence, z_um=z_um))

Each endpoint is described once (`_Call`: method, route, body, how to read the
reply); the two clients differ only in how they send it. A request that may be sent
twice with one effect (every read, a prior map, a measurement: the estimator answers
a repeat as it answered the first) is sent again after a connection error, after the
pauses of `retry_pauses_s`: behind a balancer, to another replica. Creating and
deleting a slide are not.

Within the caller's trace, each attempt is a client span of OpenTelemetry
(``GET /v1/slides/{slide_id}/next``) whose W3C trace context goes in the request's headers
(``traceparent``), so the estimator's span of it joins that trace; a no-op unless the caller
has configured an OpenTelemetry SDK (the FocusTrack services do, when told where to send
traces).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from types import TracebackType
from typing import Generic, Literal, NamedTuple, Self, TypeVar
from urllib.parse import quote

import httpx
from opentelemetry import propagate, trace
from pydantic import BaseModel, TypeAdapter

from focustrack_client.errors import raise_for_error
from focustrack_client.models import (
    NEXT_CURSOR_HEADER,
    Diagnostics,
    FocusMapOut,
    Health,
    MeasurementIn,
    Next,
    OutcomeOut,
    Slide,
    SlideCreate,
    SlideSummary,
    StrategyInfo,
)

#: Formats of `GET /v1/slides/{id}/map` other than JSON, as raw bytes.
MapFormat = Literal["csv", "npy", "png"]

#: Pauses before each new attempt of an idempotent request that met a connection error, s.
RETRY_PAUSES_S = (0.1, 0.3, 1.0)

#: The media type of a file sent as a body (a prior map's .npy), as the map's is served.
FILE_MEDIA_TYPE = "application/octet-stream"

_SUMMARIES = TypeAdapter(list[SlideSummary])
_STRATEGIES = TypeAdapter(list[StrategyInfo])

_tracer = trace.get_tracer("focustrack_client")

T = TypeVar("T")
M = TypeVar("M", bound=BaseModel)


class SlidePage(NamedTuple):
    """One page of the slide listing: its slides, oldest first, and the cursor of the next
    page (None on the last), which the service sends in a header beside the JSON array."""

    slides: list[SlideSummary]
    next_cursor: str | None


@dataclass(frozen=True)
class _Call(Generic[T]):
    """One request and how to read its reply (`read` gets the successful response). `route`:
    the path, with ``{slide_id}`` standing for `slide_id`. `body`: a model (sent as JSON) or
    a file's bytes. `idempotent`: sending it twice has the effect of once, so it may be sent
    again after a connection error."""

    method: str
    route: str
    read: Callable[[httpx.Response], T]
    body: BaseModel | bytes | None = None
    params: dict[str, str] = field(default_factory=dict)
    idempotent: bool = True
    slide_id: str | None = None

    @property
    def path(self) -> str:
        if self.slide_id is None:
            return self.route
        return self.route.format(slide_id=_path_segment(self.slide_id))

    def span(self) -> AbstractContextManager[trace.Span]:
        """A client span of one attempt, current while the block runs: in the caller's trace,
        none outside one (which costs nothing, as when the caller does not trace)."""
        if not trace.get_current_span().get_span_context().is_valid:
            return nullcontext(trace.INVALID_SPAN)
        return _tracer.start_as_current_span(
            f"{self.method} {self.route}",
            kind=trace.SpanKind.CLIENT,
            attributes={"http.request.method": self.method, "url.template": self.route},
        )

    def request(self, http: httpx.Client | httpx.AsyncClient) -> httpx.Request:
        """The request, with the current span's trace context in its headers."""
        content: str | bytes | None = None
        headers: dict[str, str] = {}
        propagate.inject(headers)
        if isinstance(self.body, bytes):
            content, headers["Content-Type"] = self.body, FILE_MEDIA_TYPE
        elif self.body is not None:
            content = self.body.model_dump_json(exclude_unset=False)
            headers["Content-Type"] = "application/json"
        return http.build_request(
            self.method, self.path, content=content, params=self.params, headers=headers
        )

    def result(self, response: httpx.Response) -> T:
        trace.get_current_span().set_attribute("http.response.status_code", response.status_code)
        raise_for_error(response)
        return self.read(response)


def _path_segment(slide_id: str) -> str:
    """`slide_id` as one segment of a path, quoted: a "?" or "#" in it names no query or
    fragment (`delete_slide("abc?x")` deleted slide abc). ValueError for an id that no
    request can carry: empty, or with a "/" (the service routes on the decoded path, so
    "abc%2Fmap" is slide abc's map; its own ids are 32 hex digits)."""
    if not slide_id or "/" in slide_id:
        raise ValueError(f"a slide id is one non-empty path segment, got {slide_id!r}")
    return quote(slide_id, safe="")


def _model(model: type[M]) -> Callable[[httpx.Response], M]:
    return lambda response: model.model_validate_json(response.content)


def _slide_page(response: httpx.Response) -> SlidePage:
    cursor = response.headers.get(NEXT_CURSOR_HEADER)
    return SlidePage(_SUMMARIES.validate_json(response.content), cursor)


def _nothing(_: httpx.Response) -> None:
    return None


def _content(response: httpx.Response) -> bytes:
    return response.content


class _Endpoints:
    """The estimator's endpoints as `_Call`s (shared by both clients)."""

    @staticmethod
    def create_slide(config: SlideCreate) -> _Call[Slide]:
        return _Call("POST", "/v1/slides", _model(Slide), body=config, idempotent=False)

    @staticmethod
    def list_slides_page(limit: int | None, cursor: str | None) -> _Call[SlidePage]:
        params = {"limit": str(limit)} if limit is not None else {}
        if cursor is not None:
            params["cursor"] = cursor
        return _Call("GET", "/v1/slides", _slide_page, params=params)

    @staticmethod
    def slide(slide_id: str) -> _Call[Slide]:
        return _Call("GET", "/v1/slides/{slide_id}", _model(Slide), slide_id=slide_id)

    @staticmethod
    def put_prior(slide_id: str, npy: bytes) -> _Call[None]:
        route = "/v1/slides/{slide_id}/prior"
        return _Call("PUT", route, _nothing, body=npy, slide_id=slide_id)

    @staticmethod
    def delete_slide(slide_id: str) -> _Call[None]:
        # a repeat after a lost reply would be a 404 for a slide that was deleted
        route = "/v1/slides/{slide_id}"
        return _Call("DELETE", route, _nothing, idempotent=False, slide_id=slide_id)

    @staticmethod
    def next(slide_id: str) -> _Call[Next]:
        return _Call("GET", "/v1/slides/{slide_id}/next", _model(Next), slide_id=slide_id)

    @staticmethod
    def measure(slide_id: str, measurement: MeasurementIn) -> _Call[OutcomeOut]:
        route = "/v1/slides/{slide_id}/measurements"
        return _Call("POST", route, _model(OutcomeOut), body=measurement, slide_id=slide_id)

    @staticmethod
    def focus_map(slide_id: str) -> _Call[FocusMapOut]:
        return _Call("GET", "/v1/slides/{slide_id}/map", _model(FocusMapOut), slide_id=slide_id)

    @staticmethod
    def focus_map_file(slide_id: str, map_format: MapFormat) -> _Call[bytes]:
        route = "/v1/slides/{slide_id}/map"
        return _Call("GET", route, _content, params={"format": map_format}, slide_id=slide_id)

    @staticmethod
    def diagnostics(slide_id: str) -> _Call[Diagnostics]:
        route = "/v1/slides/{slide_id}/diagnostics"
        return _Call("GET", route, _model(Diagnostics), slide_id=slide_id)

    @staticmethod
    def strategies() -> _Call[list[StrategyInfo]]:
        return _Call("GET", "/v1/strategies", lambda r: _STRATEGIES.validate_json(r.content))

    @staticmethod
    def health() -> _Call[Health]:
        return _Call("GET", "/healthz", _model(Health))


def _pauses(call: _Call[T], retry_pauses_s: tuple[float, ...]) -> tuple[float | None, ...]:
    """Each attempt's pause before the next (None: the last attempt, whose error is raised)."""
    return (*(retry_pauses_s if call.idempotent else ()), None)


def _checked(base_url: str, token: str | None) -> tuple[str, dict[str, str]]:
    """The base URL and the headers of a client; ValueError, at once, for what no attempt
    can send (they were httpx's errors at the first request, after its retries): a URL
    with no http(s) scheme, a token with characters a header cannot hold. A token read from
    a file keeps its line's end: the whitespace around it is left out."""
    if not base_url.lower().startswith(("http://", "https://")):
        raise ValueError(f"base_url must start with http:// or https://, got {base_url!r}")
    token = token.strip() if token else token
    if not token:
        return base_url, {}
    if not token.isascii() or not token.isprintable():
        raise ValueError("the token holds characters an HTTP header cannot carry")
    return base_url, {"Authorization": f"Bearer {token}"}


class EstimatorClient:
    """Blocking client of one estimator service (`base_url` such as http://127.0.0.1:8100).

    `token` is the service's bearer token, where it has one; `timeout_s` bounds
    every request; `retry_pauses_s`: the pauses before each new attempt of an idempotent
    request after a connection error (empty: none). `transport` replaces the network
    (for an in-process app).
    """

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout_s: float = 10.0,
        transport: httpx.BaseTransport | None = None,
        retry_pauses_s: Sequence[float] = RETRY_PAUSES_S,
    ) -> None:
        base_url, headers = _checked(base_url, token)
        self.http = httpx.Client(
            base_url=base_url, headers=headers, timeout=timeout_s, transport=transport
        )
        self.retry_pauses_s = tuple(retry_pauses_s)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _send(self, call: _Call[T]) -> T:
        for pause_s in _pauses(call, self.retry_pauses_s):
            try:
                with call.span():
                    return call.result(self.http.send(call.request(self.http)))
            except httpx.TransportError:
                if pause_s is None:
                    raise
                time.sleep(pause_s)
        raise AssertionError("unreachable: the last attempt returns or raises")

    def create_slide(self, config: SlideCreate) -> Slide:
        """A new slide, scanned as `config` says; its id is `.id`."""
        return self._send(_Endpoints.create_slide(config))

    def list_slides(self) -> list[SlideSummary]:
        """Every slide, oldest first (every page of the listing, `iter_slides`)."""
        return list(self.iter_slides())

    def list_slides_page(self, limit: int | None = None, cursor: str | None = None) -> SlidePage:
        """One page of slides, oldest first (`limit` of them, the service's default if
        None), from `cursor` (the previous page's `next_cursor`; None: the first page)."""
        return self._send(_Endpoints.list_slides_page(limit, cursor))

    def iter_slides(self, page_size: int | None = None) -> Iterator[SlideSummary]:
        """Every slide, oldest first, fetched a page of `page_size` at a time (the
        service's default if None) as the iteration reaches it."""
        cursor: str | None = None
        while True:
            page = self.list_slides_page(page_size, cursor)
            yield from page.slides
            if (cursor := page.next_cursor) is None:
                return

    def slide(self, slide_id: str) -> Slide:
        return self._send(_Endpoints.slide(slide_id))

    def put_prior(self, slide_id: str, npy: bytes) -> None:
        """Make the .npy file `npy` the prior map of a slide not yet scanned (kf-rescan):
        heights (rows, cols), or heights and their sigmas (2, rows, cols), um."""
        self._send(_Endpoints.put_prior(slide_id, npy))

    def delete_slide(self, slide_id: str) -> None:
        self._send(_Endpoints.delete_slide(slide_id))

    def next(self, slide_id: str) -> Next:
        """The next tile and z-range to acquire (`.done` once the scan is complete)."""
        return self._send(_Endpoints.next(slide_id))

    def measure(self, slide_id: str, measurement: MeasurementIn) -> OutcomeOut:
        """Report the best focus found for the acquisition `measurement.sequence`."""
        return self._send(_Endpoints.measure(slide_id, measurement))

    def focus_map(self, slide_id: str) -> FocusMapOut:
        return self._send(_Endpoints.focus_map(slide_id))

    def focus_map_file(self, slide_id: str, map_format: MapFormat) -> bytes:
        """The map as a CSV, .npy or PNG file's bytes."""
        return self._send(_Endpoints.focus_map_file(slide_id, map_format))

    def diagnostics(self, slide_id: str) -> Diagnostics:
        return self._send(_Endpoints.diagnostics(slide_id))

    def strategies(self) -> list[StrategyInfo]:
        """The strategies the service serves, each with its parameters' JSON schema and
        defaults (what `SlideCreate.strategy` and `.params` take)."""
        return self._send(_Endpoints.strategies())

    def health(self) -> Health:
        return self._send(_Endpoints.health())


class AsyncEstimatorClient:
    """The same client for asyncio: every method is a coroutine (`async with` closes it)."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout_s: float = 10.0,
        transport: httpx.AsyncBaseTransport | None = None,
        retry_pauses_s: Sequence[float] = RETRY_PAUSES_S,
    ) -> None:
        base_url, headers = _checked(base_url, token)
        self.http = httpx.AsyncClient(
            base_url=base_url, headers=headers, timeout=timeout_s, transport=transport
        )
        self.retry_pauses_s = tuple(retry_pauses_s)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self.http.aclose()

    async def _send(self, call: _Call[T]) -> T:
        for pause_s in _pauses(call, self.retry_pauses_s):
            try:
                with call.span():
                    return call.result(await self.http.send(call.request(self.http)))
            except httpx.TransportError:
                if pause_s is None:
                    raise
                await asyncio.sleep(pause_s)
        raise AssertionError("unreachable: the last attempt returns or raises")

    async def create_slide(self, config: SlideCreate) -> Slide:
        return await self._send(_Endpoints.create_slide(config))

    async def list_slides(self) -> list[SlideSummary]:
        return [slide async for slide in self.iter_slides()]

    async def list_slides_page(
        self, limit: int | None = None, cursor: str | None = None
    ) -> SlidePage:
        return await self._send(_Endpoints.list_slides_page(limit, cursor))

    async def iter_slides(self, page_size: int | None = None) -> AsyncIterator[SlideSummary]:
        cursor: str | None = None
        while True:
            page = await self.list_slides_page(page_size, cursor)
            for slide in page.slides:
                yield slide
            if (cursor := page.next_cursor) is None:
                return

    async def slide(self, slide_id: str) -> Slide:
        return await self._send(_Endpoints.slide(slide_id))

    async def put_prior(self, slide_id: str, npy: bytes) -> None:
        await self._send(_Endpoints.put_prior(slide_id, npy))

    async def delete_slide(self, slide_id: str) -> None:
        await self._send(_Endpoints.delete_slide(slide_id))

    async def next(self, slide_id: str) -> Next:
        return await self._send(_Endpoints.next(slide_id))

    async def measure(self, slide_id: str, measurement: MeasurementIn) -> OutcomeOut:
        return await self._send(_Endpoints.measure(slide_id, measurement))

    async def focus_map(self, slide_id: str) -> FocusMapOut:
        return await self._send(_Endpoints.focus_map(slide_id))

    async def focus_map_file(self, slide_id: str, map_format: MapFormat) -> bytes:
        return await self._send(_Endpoints.focus_map_file(slide_id, map_format))

    async def diagnostics(self, slide_id: str) -> Diagnostics:
        return await self._send(_Endpoints.diagnostics(slide_id))

    async def strategies(self) -> list[StrategyInfo]:
        return await self._send(_Endpoints.strategies())

    async def health(self) -> Health:
        return await self._send(_Endpoints.health())
