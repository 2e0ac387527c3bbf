"""The hostile requests (`focustrack.bench.hostile.fire`, which the chaos bench
sends) against a real estimator process and a real focus server: no 5xx, each refused
with the status that says why, and the slides it may create kept within the budget."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import httpx
from fastapi import FastAPI

from focustrack.bench.hostile import fire
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn
from focustrack_focus.app import create_app

#: What each request must get from services on their default settings.
EXPECTED = {
    "kf2d-bank-20": 422,
    "gp-oracle-500": 422,
    "kf2d-250x750": 422,
    "sigma-1e-300": 422,
    "many-slides": 201,
    "tiff-bomb": 413,
    "npy-huge-shape": 413,
    "zero-size-frames": 422,
    "large-lowpass": 422,
    "json-deep": 422,
    "json-59mb": 413,
}


def test_every_hostile_request_is_refused_without_a_5xx(
    http: httpx.Client, tmp_path: Path, serve: Callable[[FastAPI], str]
) -> None:
    port = free_port()
    process = spawn(
        tmp_path / "hostile.sqlite",
        port,
        "t0ken",
        timeout_s=120,
        options=["--max-live-slides", "5"],
    )
    try:
        estimator = f"http://127.0.0.1:{port}"
        focus = serve(create_app(token="f0cus"))
        statuses = fire(estimator, focus, estimator_token="t0ken", focus_token="f0cus", n_slides=12)
        assert not [name for name, status in statuses.items() if status >= 500], statuses
        assert statuses == EXPECTED
        auth = {"Authorization": "Bearer t0ken"}
        assert len(http.get(f"{estimator}/v1/slides", headers=auth).json()) == 12
        live = re.search(r"^\w+_live_slides (\d+)", http.get(f"{estimator}/metrics").text, re.M)
        assert live and int(live[1]) <= 5
    finally:
        process.terminate()
        assert process.wait(60) == 0
