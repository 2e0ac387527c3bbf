"""The gates in front of /v1, each refusing before the body is read: `BearerGate`, a request
without the token; `ConcurrencyLimit`, one more than the service takes at once."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from urllib.parse import urlsplit

import httpx
import pytest

from focustrack_core.serving import (
    BackgroundServer,
    BearerGate,
    ConcurrencyLimit,
    Message,
    Receive,
    Scope,
    Send,
)


class RecordingApp:
    """An ASGI app that reads the whole body and answers how many bytes it read."""

    def __init__(self) -> None:
        self.paths: list[str] = []

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        assert scope["type"] == "http"
        self.paths.append(scope["path"])
        size, more = 0, True
        while more:
            message: Message = await receive()
            size += len(message.get("body", b""))
            more = message.get("more_body", False)
        body = json.dumps({"read_bytes": size}).encode()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": body})


@pytest.fixture
def served() -> Iterator[tuple[RecordingApp, str]]:
    inner = RecordingApp()
    gate = BearerGate(inner, token="s3cret", error_body=lambda detail: {"detail": detail})
    with BackgroundServer(gate) as server:
        yield inner, server.url


def test_a_request_without_the_token_never_reaches_the_app(
    http: httpx.Client,
    served: tuple[RecordingApp, str],
) -> None:
    inner, url = served
    upload = b"\0" * (4 << 20)  # a stack's worth: the app would have read all of it
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic s3cret"}):
        refused = http.post(f"{url}v1/phase/stack", content=upload, headers=headers)
        assert refused.status_code == 401, refused.text
        assert refused.json() == {"detail": "missing or wrong bearer token"}
        assert refused.headers["www-authenticate"] == "Bearer"
    assert inner.paths == []


def test_the_token_lets_a_request_through_and_other_paths_are_open(
    http: httpx.Client,
    served: tuple[RecordingApp, str],
) -> None:
    inner, url = served
    passed = http.post(
        f"{url}v1/phase/stack", content=b"12345", headers={"Authorization": "bearer s3cret"}
    )
    assert passed.status_code == 200 and passed.json() == {"read_bytes": 5}
    for path in ("healthz", "metrics", "v10/anything", "openapi.json"):
        assert http.get(f"{url}{path}").status_code == 200, path
    assert http.get(f"{url}v1").status_code == 401  # the prefix itself is guarded
    assert inner.paths == [
        "/v1/phase/stack",
        "/healthz",
        "/metrics",
        "/v10/anything",
        "/openapi.json",
    ]


def _start_slow_request(url: str, path: str, body_bytes: int) -> socket.socket:
    """A connection whose request to `path` has sent its headers and half of its body:
    under way until the rest is sent."""
    parts = urlsplit(url)
    connection = socket.create_connection((parts.hostname, parts.port), timeout=10)
    head = f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {body_bytes}\r\n\r\n"
    connection.sendall(head.encode() + b"\0" * (body_bytes // 2))
    return connection


def test_one_request_beyond_the_bound_is_refused_at_once_and_the_place_freed_after(
    http: httpx.Client,
) -> None:
    inner = RecordingApp()
    limit = ConcurrencyLimit(inner, max_concurrent=1, error_body=lambda d: {"detail": d})
    with BackgroundServer(limit) as server:
        slow = _start_slow_request(server.url, "/v1/phase/stack", 10)
        with slow:
            for _ in range(100):  # until the server has taken the slow request in
                refused = http.post(f"{server.url}v1/phase/stack", content=b"\0" * (4 << 20))
                if refused.status_code == 503:
                    break
                time.sleep(0.05)
            assert refused.status_code == 503, refused.text
            assert refused.headers["retry-after"] == "1"
            assert "the most requests it takes at once (1)" in refused.json()["detail"]
            assert http.get(f"{server.url}healthz").status_code == 200  # not under /v1
            slow.sendall(b"\0" * 5)
            answer = b""
            while not answer.endswith(b"0\r\n\r\n"):  # the chunked body's end
                chunk = slow.recv(4096)
                assert chunk, answer  # closed before the whole answer
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 200") and b'{"read_bytes": 10}' in answer
        again = http.post(f"{server.url}v1/phase/stack", content=b"123")
        assert again.status_code == 200 and again.json() == {"read_bytes": 3}
    assert inner.paths[-2:] == ["/healthz", "/v1/phase/stack"]  # the 503s never reached it


def test_a_bound_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="max_concurrent must be at least 1, got 0"):
        ConcurrencyLimit(RecordingApp(), max_concurrent=0, error_body=lambda d: {"detail": d})
