"""Safe network defaults: off loopback the estimator refuses to start without a token unless
--insecure; with one, /v1 requires it. Each a `python -m focustrack_estimator` of its own."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx

from focustrack_core.wire.session import free_port


def _run(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "focustrack_estimator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **(env or {})},
    )


def test_the_estimator_refuses_the_network_without_a_token(tmp_path: Path) -> None:
    store = str(tmp_path / "e.sqlite")
    process = _run("--host", "0.0.0.0", "--port", str(free_port()), "--store", store)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 2, (out, err)
    assert "without a token" in err and "--insecure" in err and "Traceback" not in err
    assert not Path(store).exists()  # refused before the store was touched


def _wait_healthy(http: httpx.Client, url: str, process: subprocess.Popen) -> None:
    deadline_s = time.monotonic() + 120
    while time.monotonic() < deadline_s:
        assert process.poll() is None, process.communicate()
        try:
            if http.get(f"{url}/healthz", timeout=1).status_code == 200:
                return
        except httpx.TransportError:
            time.sleep(0.1)
    raise AssertionError(f"{url} did not become healthy")


def test_the_estimator_on_the_network_with_a_token_or_insecure(
    http: httpx.Client, tmp_path: Path
) -> None:
    slide = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 2}}
    for env, headers, status in (
        ({"FOCUSTRACK_ESTIMATOR_TOKEN": "s3cret"}, {}, 401),
        ({"FOCUSTRACK_ESTIMATOR_TOKEN": "s3cret"}, {"Authorization": "Bearer s3cret"}, 201),
        ({"FOCUSTRACK_ESTIMATOR_INSECURE": "1"}, {}, 201),
    ):
        port = free_port()
        store = str(tmp_path / f"{port}.sqlite")
        process = _run("--host", "0.0.0.0", "--port", str(port), "--store", store, env=env)
        try:
            url = f"http://127.0.0.1:{port}"
            _wait_healthy(http, url, process)
            # The first slide waits for the strategies, which load once the service serves:
            # on a busy machine that is longer than httpx's default 5 s.
            reply = http.post(f"{url}/v1/slides", json=slide, headers=headers, timeout=60)
            assert reply.status_code == status
        finally:
            process.terminate()
            process.wait(60)
