"""The servers' edges: a request body that trickles in is timed out (408) rather
than holding a connection forever, and error replies quote at most 200 characters of an
input (a 1 MB input is not echoed). Real servers on loopback."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator

import httpx
import numpy as np
import pytest
from fastapi import FastAPI

from focustrack_core.serving import MAX_QUOTED_CHARS, cut
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn
from focustrack_focus.app import FocusLimits, create_app


@pytest.fixture(scope="module")
def estimator(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = free_port()
    options = ["--body-timeout-s", "1", "--max-body-bytes", str(4 * 2**20)]
    store = tmp_path_factory.mktemp("edge") / "edge.sqlite"
    process = spawn(store, port, timeout_s=120, options=options)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(60)


def _trickle(url: str, path: str, declared: int, pieces: list[bytes], pause_s: float) -> bytes:
    """Send headers declaring `declared` bytes, then `pieces` `pause_s` apart; the reply."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        head = f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n"
        sock.sendall(f"{head}Content-Length: {declared}\r\n\r\n".encode())
        reply = b""
        try:
            for piece in pieces:
                sock.sendall(piece)
                time.sleep(pause_s)
        except OSError:  # the server gave up on us: its answer is what follows
            pass
        while chunk := sock.recv(4096):
            reply += chunk
        return reply


def test_a_stalled_or_trickling_body_gets_408_from_the_estimator(
    http: httpx.Client, estimator: str
) -> None:
    stalled = _trickle(estimator, "/v1/slides", 1000, [b'{"strategy": '], 0.0)
    assert stalled.startswith(b"HTTP/1.1 408"), stalled
    assert b"did not arrive within 1 s" in stalled
    # A byte every 0.2 s never lets a per-read timeout fire; the whole body is timed.
    trickling = _trickle(estimator, "/v1/slides", 1000, [b" "] * 30, 0.2)
    assert trickling.startswith(b"HTTP/1.1 408"), trickling
    assert http.get(f"{estimator}/healthz").status_code == 200  # and the service goes on
    body = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 2}}
    assert http.post(f"{estimator}/v1/slides", json=body).status_code == 201


def test_a_stalled_body_gets_408_from_the_focus_service(
    http: httpx.Client,
    serve: Callable[[FastAPI], str],
) -> None:
    url = serve(create_app(limits=FocusLimits(body_timeout_s=1.0)))
    stalled = _trickle(url, "/v1/focus/curve", 1000, [b'{"z_um": [1, '], 0.0)
    assert stalled.startswith(b"HTTP/1.1 408"), stalled
    curve = {"z_um": [0, 1, 2], "scores": [1, 2, 1]}
    assert http.post(f"{url}/v1/focus/curve", json=curve).status_code == 200


def _short(response: httpx.Response, needle: str, quoted: bool = True) -> None:
    """A 4xx naming the problem in under 2 kB; `quoted`: it quotes the input, cut."""
    assert 400 <= response.status_code < 500, response.text
    assert len(response.content) < 2_000, len(response.content)
    assert needle in response.text, response.text
    assert ("(cut: " in response.text) == quoted, response.text


def test_the_estimator_does_not_echo_a_megabyte(http: httpx.Client, estimator: str) -> None:
    huge = "x" * 1_000_000
    grid = {"rows": 2, "cols": 2}
    value = http.post(
        f"{estimator}/v1/slides",
        json={"strategy": "kf-wiener0", "grid": grid, "params": {"q": huge}},
    )
    _short(value, "a valid number")
    key = http.post(
        f"{estimator}/v1/slides", json={"strategy": "kf-wiener0", "grid": grid, huge: 1}
    )
    _short(key, "Extra inputs are not permitted")


def test_the_focus_service_does_not_echo_a_megabyte(
    http: httpx.Client, serve: Callable[[FastAPI], str]
) -> None:
    url = serve(create_app())
    frames = np.zeros((3, 8, 8), np.uint16).tobytes()
    huge = "y" * 1_000_000
    for form, needle, quoted in (
        ({"z_um": "0,1,2", "metric": huge}, "unknown focus metric", True),
        ({"z_um": huge}, "z_um must be finite numbers", True),  # the item quoted, cut
    ):
        response = http.post(
            f"{url}/v1/focus/stack", files={"stack": ("s.npy", frames)}, data=form, timeout=60
        )
        _short(response, needle, quoted)


def test_cut_keeps_short_texts_and_notes_the_length_of_long_ones() -> None:
    assert cut("short") == "short"
    text = "z" * (MAX_QUOTED_CHARS + 1)
    assert cut(text) == "z" * MAX_QUOTED_CHARS + f"... (cut: {len(text)} characters in all)"
