"""What every HTTP service of FocusTrack shares at its edge: safe defaults, pure ASGI.

- `refuse_open_network`: off loopback a service needs a token (or `--insecure`).
- `SlowBodyTimeout`: an ASGI middleware that aborts a request whose body trickles
  in too slowly (uvicorn's `timeout_keep_alive` only covers idle connections).
- `cut`: error messages quote at most `MAX_QUOTED_CHARS` of an input; `quoted_errors`
  the validation errors of a 422 likewise, without the inputs.
- `BackgroundServer`: an ASGI app served by uvicorn on a thread of its own (the live
  view of a scan, tests).
- `RequestTimer`: an ASGI middleware that hands each request's method, route template,
  status and seconds to a callback (the services' Prometheus metrics).
- `BearerGate`: an ASGI middleware that refuses (401) a request under a path prefix
  without the service's bearer token, before anything reads its body.

No web framework is imported: the middleware speaks plain ASGI, and uvicorn is
imported by `BackgroundServer` alone (what serves an app has it), so the core gains
no dependency.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import os
import secrets
import signal
import socket
import threading
import time
from collections.abc import Awaitable, Callable, Mapping, MutableMapping, Sequence
from typing import Any

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: Characters of an input an error message may quote; the rest is left out, with a note.
MAX_QUOTED_CHARS = 200
#: Characters of an error's message: the service's own words (a list of what it knows, of
#: what it serves), with the inputs they quote bounded by their models (names of 64).
MAX_MESSAGE_CHARS = 1000


def cut(text: str, limit: int = MAX_QUOTED_CHARS) -> str:
    """`text` if at most `limit` characters, else its start and a note of how long it was."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... (cut: {len(text)} characters in all)"


def quoted_errors(errors: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """A 422's validation errors (pydantic's `errors()`): where and what is wrong, cut."""
    # FastAPI's own handler echoes each bad input, and a NaN there cannot be written as
    # JSON (a 500), a long one makes a long reply: give where and what, not the input.
    return [
        {
            "loc": [cut(part) if isinstance(part, str) else part for part in item["loc"]],
            "msg": cut(item["msg"], MAX_MESSAGE_CHARS),
            "type": item["type"],
        }
        for item in errors
    ]


def is_loopback(host: str) -> bool:
    """Whether binding `host` exposes the service to this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def http_url(host: str, port: int, path: str = "") -> str:
    """The URL of `path` on an HTTP server at `host`:`port`; an IPv6 address in brackets
    (RFC 3986: ``http://[::1]:8100``, where ``http://::1:8100`` is no URL)."""
    return f"http://[{host}]:{port}{path}" if ":" in host else f"http://{host}:{port}{path}"


def refuse_open_network(service: str, host: str, token: str | None, insecure: bool) -> str | None:
    """Why `service` must not start on `host` without a token (None: it may start).

    On loopback only local processes reach it; anywhere else an open API lets any
    host on the network drive it, so a token is required unless `insecure` is given.
    """
    if token or insecure or is_loopback(host):
        return None
    prefix = f"FOCUSTRACK_{service.upper()}_"
    return (
        f"refusing to serve the {service} API on {host} without a token: anyone on the "
        f"network could use it. Set --token (or {prefix}TOKEN), bind to 127.0.0.1, or pass "
        f"--insecure ({prefix}INSECURE=1) to run it open on purpose"
    )


async def send_json_and_close(
    send: Send, status: int, body: Any, headers: Sequence[tuple[bytes, bytes]] = ()
) -> None:
    """Answer `status` with `body` as JSON and close the connection: the middleware's
    refusals, sent before (or instead of) reading the request's body, which would
    otherwise be left unread on a connection kept alive."""
    payload = json.dumps(body).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(payload)).encode()),
                (b"connection", b"close"),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": payload})


class SlowBodyTimeout:
    """ASGI middleware: a request body must arrive whole within `timeout_s` of the request.

    A client that sends its headers and then trickles its body (or stops) would
    otherwise hold a connection and a request task forever. When the time is up
    while the body is still incomplete, the route is cancelled and the client gets
    `status` with `error_body` (JSON) and the connection is closed. Requests
    without a body, and routes that answer before reading theirs, are not timed.
    """

    def __init__(
        self, app: ASGIApp, *, timeout_s: float, error_body: dict[str, Any], status: int = 408
    ) -> None:
        if not timeout_s > 0:
            raise ValueError(f"the body timeout must be positive, got {timeout_s}")
        self.app, self.timeout_s, self.status = app, timeout_s, status
        self.error = error_body

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = dict(scope.get("headers") or ()) if scope["type"] == "http" else {}
        declared = headers.get(b"content-length", b"0")
        has_body = b"transfer-encoding" in headers or (declared.isdigit() and int(declared) > 0)
        if not has_body:
            await self.app(scope, receive, send)
            return
        body_done = asyncio.Event()
        started = False

        async def tracked_receive() -> Message:
            message = await receive()
            if message["type"] != "http.request" or not message.get("more_body", False):
                body_done.set()
            return message

        async def tracked_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        route = asyncio.ensure_future(self.app(scope, tracked_receive, tracked_send))
        body = asyncio.ensure_future(body_done.wait())
        try:
            await asyncio.wait({route, body}, timeout=self.timeout_s, return_when="FIRST_COMPLETED")
        except BaseException:  # this request cancelled (shutdown): its route with it
            route.cancel()
            raise
        finally:
            body.cancel()
        if not route.done() and not body_done.is_set() and not started:
            route.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await route
            await send_json_and_close(send, self.status, self.error)
            return
        await route


class RequestTimer:
    """ASGI middleware: `observe(method, route, status, seconds)` after every HTTP request,
    with the route's template (``/v1/slides/{slide_id}``, not the id; ``unmatched`` where
    no route matched) and the status sent (500 if none was).

    A request the middleware refused before routing (a 413 by its declared length, a 401
    without the token) has no route in its scope: `route_of(scope)`, where given, finds the
    template it was addressed to, so a refusal counts against its route too.
    """

    def __init__(
        self,
        app: ASGIApp,
        observe: Callable[[str, str, int, float], None],
        route_of: Callable[[Scope], str | None] | None = None,
    ) -> None:
        self.app, self.observe, self.route_of = app, observe, route_of

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start_s = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None)
            if route is None and self.route_of is not None:
                route = self.route_of(scope)
            self.observe(
                scope["method"], route or "unmatched", status, time.perf_counter() - start_s
            )


class _BodyTooLargeError(Exception):
    """Raised inside a route's `receive` once its body passed the limit."""


class BodyLimit:
    """ASGI middleware: refuse request bodies over `max_bytes` with a 413 that says the limit.

    A declared Content-Length over the limit is refused before anything is read; a
    body streamed without one is counted as it arrives, and once over the limit the
    route is stopped (what it would answer is dropped) and the 413 sent instead.
    `error_body(message)` is the JSON of the reply, in the service's error shape.
    """

    def __init__(
        self, app: ASGIApp, *, max_bytes: int, error_body: Callable[[str], dict[str, Any]]
    ) -> None:
        self.app, self.max_bytes, self.error_body = app, max_bytes, error_body

    async def _refuse(self, send: Send, size: str) -> None:
        message = f"request body of {size} exceeds the limit of {self.max_bytes} bytes"
        await send_json_and_close(send, 413, self.error_body(message))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.max_bytes:
            await self._refuse(send, f"{int(declared)} bytes")
            return
        received, over, started = 0, False, False

        async def limited() -> Message:
            nonlocal received, over
            message = await receive()
            received += len(message.get("body", b""))
            if received > self.max_bytes:
                over = True
                raise _BodyTooLargeError
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if over:  # the route's answer to the aborted body (a 400 or 500): ours instead
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited, guarded_send)
        except Exception:
            if not over:
                raise
        if over and not started:
            await self._refuse(send, f"more than {received} bytes")


class BearerGate:
    """ASGI middleware: a 401 for a request under `prefix` (``/v1``: the path itself or
    below it) unless its ``Authorization`` is ``Bearer`` and `token`, compared in constant
    time; other paths (``/healthz``, ``/metrics``, the OpenAPI document) pass.

    The check runs before anything reads the body: a framework parses a route's body (a
    multipart stack of hundreds of MB, spooled to disk) before its dependencies run, so a
    token checked there lets anyone without it make the service read that much.
    `error_body(message)` is the JSON of the reply, in the service's error shape.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        token: str,
        error_body: Callable[[str], dict[str, Any]],
        prefix: str = "/v1",
    ) -> None:
        self.app, self.token, self.error_body = app, token.encode(), error_body
        self.prefix = prefix.rstrip("/")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not _under(scope["path"], self.prefix):
            await self.app(scope, receive, send)
            return
        authorization = dict(scope["headers"]).get(b"authorization", b"")
        scheme, _, credentials = authorization.partition(b" ")
        if scheme.lower() == b"bearer" and secrets.compare_digest(credentials.strip(), self.token):
            await self.app(scope, receive, send)
            return
        body = self.error_body("missing or wrong bearer token")
        await send_json_and_close(send, 401, body, [(b"www-authenticate", b"Bearer")])


class ConcurrencyLimit:
    """ASGI middleware: at most `max_concurrent` requests under `prefix` (``/v1``: the path
    itself or below it) at once; one more is answered 503 with ``Retry-After:
    retry_after_s`` straight away, before its body is read, rather than held. A request
    counts from its arrival until its answer is sent.

    What bounds a service's memory: each phase reconstruction holds its upload, the stack
    decoded and the filter's arrays (six uploads of 252 MB at once took 4.5 GB).
    `error_body(message)` is the JSON of the reply, in the service's error shape.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        max_concurrent: int,
        error_body: Callable[[str], dict[str, Any]],
        prefix: str = "/v1",
        retry_after_s: int = 1,
    ) -> None:
        if max_concurrent < 1:
            raise ValueError(f"max_concurrent must be at least 1, got {max_concurrent}")
        self.app, self.max_concurrent, self.error_body = app, max_concurrent, error_body
        self.prefix, self.retry_after_s = prefix.rstrip("/"), retry_after_s
        self.under_way = 0  # one event loop: no lock needed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not _under(scope["path"], self.prefix):
            await self.app(scope, receive, send)
            return
        if self.under_way >= self.max_concurrent:
            body = self.error_body(
                "the service is busy with the most requests it takes at once "
                f"({self.max_concurrent}); ask again in {self.retry_after_s} s"
            )
            retry_after = (b"retry-after", str(self.retry_after_s).encode())
            await send_json_and_close(send, 503, body, [retry_after])
            return
        self.under_way += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.under_way -= 1


def _under(path: str, prefix: str) -> bool:
    """Whether the URL `path` is `prefix` itself or below it (``/v1``, not ``/v10``)."""
    return path == prefix or path.startswith(prefix + "/")


class ListenError(OSError):
    """A server cannot listen on its address (in use, or not permitted)."""

    @classmethod
    def of(cls, name: str, host: str, port: int, error: OSError) -> ListenError:
        """The error of the `name` server that `error` kept from `host`:`port`, in words."""
        if error.errno is None:
            reason = str(error)
        elif error.errno < 0:  # getaddrinfo's (EAI_NONAME is -2), which strerror does not know
            reason = f"{host!r} does not resolve to an address"
        else:
            reason = os.strerror(error.errno)
        return cls(f"the {name} server cannot listen on {host}:{port}: {reason}")


def listening_socket(host: str, port: int, name: str) -> socket.socket:
    """A TCP socket listening on `host`:`port` for the `name` server; ListenError, which
    names the server and the address, when it cannot be had."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        return socket.create_server((host, port), family=family)
    except OSError as error:
        raise ListenError.of(name, host, port, error) from error


def serve_until_stopped(app: ASGIApp, listening: socket.socket, **options: Any) -> None:
    """`app` served by uvicorn on the socket `listening` (`listening_socket`: bound before the
    service says where it is, so a port in use is a ListenError, not uvicorn's exit 3 after
    that line), in this thread, until SIGINT or SIGTERM (`docker stop`). `options` go to
    `uvicorn.Config` (log_level, access_log, ...).

    uvicorn shuts down gracefully on SIGINT or SIGTERM and then raises the signal again,
    which with the default handlers kills the process (status -15) or raises a
    KeyboardInterrupt (a traceback) before the caller's `finally` has closed its store or
    its Zenoh session: handlers of ours take that second delivery, and the service ends
    with status 0.
    """
    import uvicorn

    host, port = listening.getsockname()[:2]
    server = uvicorn.Server(uvicorn.Config(app, host=host, port=port, **options))
    stops = (signal.SIGINT, signal.SIGTERM)
    previous = {stop: signal.signal(stop, lambda *_: None) for stop in stops}
    try:
        server.run(sockets=[listening])
    finally:
        for stop, handler in previous.items():
            signal.signal(stop, handler)
        listening.close()


class BackgroundServer:
    """`app` served on http://`host`:`port`/ by uvicorn in a daemon thread; a context manager.

    `port` 0 takes a free one (`url` says which, once started). The socket is bound in the
    caller's thread, so an address in use is a ListenError there.
    """

    def __init__(
        self, app: ASGIApp, host: str = "127.0.0.1", port: int = 0, name: str = "http"
    ) -> None:
        import uvicorn

        self._server = uvicorn.Server(
            uvicorn.Config(app, host=host, port=port, log_level="warning")
        )
        self._address = (host, port)
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._socket: socket.socket | None = None

    def _serve(self) -> None:
        assert self._socket is not None  # `start` bound it
        self._server.run(sockets=[self._socket])

    @property
    def url(self) -> str:
        host, port = self._server.servers[0].sockets[0].getsockname()[:2]
        return http_url(host, port, "/")

    def start(self, timeout_s: float = 30.0) -> BackgroundServer:
        """Start serving; ListenError if its address cannot be had, RuntimeError if the
        server is not up within `timeout_s`."""
        self._socket = listening_socket(*self._address, self._thread.name)
        self._thread.start()
        deadline_s = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline_s:
                raise RuntimeError(f"the {self._thread.name} server did not start")
            time.sleep(0.02)
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        self._server.should_exit = True
        self._thread.join(timeout_s)
        if self._socket is not None:
            self._socket.close()

    def __enter__(self) -> BackgroundServer:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()
