"""`BearerGate`: a request under /v1 without the token is refused before its body is read."""

from __future__ import annotations

import json
from collections.abc import Iterator

import httpx
import pytest

from focustrack_core.serving import BackgroundServer, BearerGate, Message, Receive, Scope, Send


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
    served: tuple[RecordingApp, str],
) -> None:
    inner, url = served
    upload = b"\0" * (4 << 20)  # a stack's worth: the app would have read all of it
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic s3cret"}):
        refused = httpx.post(f"{url}v1/phase/stack", content=upload, headers=headers)
        assert refused.status_code == 401, refused.text
        assert refused.json() == {"detail": "missing or wrong bearer token"}
        assert refused.headers["www-authenticate"] == "Bearer"
    assert inner.paths == []


def test_the_token_lets_a_request_through_and_other_paths_are_open(
    served: tuple[RecordingApp, str],
) -> None:
    inner, url = served
    passed = httpx.post(
        f"{url}v1/phase/stack", content=b"12345", headers={"Authorization": "bearer s3cret"}
    )
    assert passed.status_code == 200 and passed.json() == {"read_bytes": 5}
    for path in ("healthz", "metrics", "v10/anything", "openapi.json"):
        assert httpx.get(f"{url}{path}").status_code == 200, path
    assert httpx.get(f"{url}v1").status_code == 401  # the prefix itself is guarded
    assert inner.paths == [
        "/v1/phase/stack",
        "/healthz",
        "/metrics",
        "/v10/anything",
        "/openapi.json",
    ]
