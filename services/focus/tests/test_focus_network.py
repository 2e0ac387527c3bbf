"""Safe network defaults: off loopback the focus service refuses to start without a token
unless --insecure; with one, /v1 requires it (and /healthz does not)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

import httpx
from fastapi import FastAPI

from focustrack_core.wire.session import free_port
from focustrack_focus.app import create_app


def test_the_focus_service_refuses_the_network_without_a_token() -> None:
    address = ["--host", "0.0.0.0", "--port", str(free_port())]
    process = subprocess.run(
        [sys.executable, "-m", "focustrack_focus", *address, "--connect", "tcp/127.0.0.1:1"],
        capture_output=True,
        text=True,
        timeout=120,
    )  # refused before any Zenoh
    assert process.returncode == 2, process
    err = process.stderr
    assert "without a token" in err and "--insecure" in err and "Traceback" not in err


def test_the_focus_api_requires_its_token(
    http: httpx.Client, serve: Callable[[FastAPI], str]
) -> None:
    url = serve(create_app(token="f0cus"))
    curve = {"z_um": [0, 1, 2], "scores": [1, 2, 1]}
    assert http.post(f"{url}/v1/focus/curve", json=curve).status_code == 401
    wrong = {"Authorization": "Bearer nope"}
    assert http.post(f"{url}/v1/focus/curve", json=curve, headers=wrong).status_code == 401
    right = {"Authorization": "Bearer f0cus"}
    assert http.post(f"{url}/v1/focus/curve", json=curve, headers=right).status_code == 200
    assert http.get(f"{url}/healthz").status_code == 200  # health checks need no token
