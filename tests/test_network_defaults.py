"""Safe network defaults: off loopback the estimator refuses to start without a
token unless --insecure; with one, /v1 requires it; compose takes the tokens from a .env file
(.env.example documents them). The focus service's own: services/focus/tests."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx

from focustrack_core.serving import is_loopback, refuse_open_network
from focustrack_core.wire.session import free_port

ROOT = Path(__file__).resolve().parents[1]


def _run(module: str, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **(env or {})},
    )


def test_loopback_is_told_apart_from_the_network() -> None:
    assert all(map(is_loopback, ["127.0.0.1", "127.0.0.2", "::1", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.1.10", "estimator"]))
    assert refuse_open_network("focus", "127.0.0.1", None, insecure=False) is None
    assert refuse_open_network("focus", "0.0.0.0", "secret", insecure=False) is None
    assert refuse_open_network("focus", "0.0.0.0", None, insecure=True) is None
    message = refuse_open_network("focus", "0.0.0.0", None, insecure=False)
    assert message and "FOCUSTRACK_FOCUS_TOKEN" in message and "--insecure" in message


def test_the_estimator_refuses_the_network_without_a_token(tmp_path: Path) -> None:
    store = str(tmp_path / "e.sqlite")
    process = _run(
        "focustrack_estimator", "--host", "0.0.0.0", "--port", str(free_port()), "--store", store
    )
    out, err = process.communicate(timeout=120)
    assert process.returncode == 2, (out, err)
    assert "without a token" in err and "--insecure" in err and "Traceback" not in err
    assert not Path(store).exists()  # refused before the store was touched


def _wait_healthy(url: str, process: subprocess.Popen) -> None:
    deadline_s = time.monotonic() + 120
    while time.monotonic() < deadline_s:
        assert process.poll() is None, process.communicate()
        try:
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return
        except httpx.TransportError:
            time.sleep(0.1)
    raise AssertionError(f"{url} did not become healthy")


def test_the_estimator_on_the_network_with_a_token_or_insecure(tmp_path: Path) -> None:
    slide = {"strategy": "kf-wiener0", "grid": {"rows": 2, "cols": 2}}
    for env, headers, status in (
        ({"FOCUSTRACK_ESTIMATOR_TOKEN": "s3cret"}, {}, 401),
        ({"FOCUSTRACK_ESTIMATOR_TOKEN": "s3cret"}, {"Authorization": "Bearer s3cret"}, 201),
        ({"FOCUSTRACK_ESTIMATOR_INSECURE": "1"}, {}, 201),
    ):
        port = free_port()
        store = str(tmp_path / f"{port}.sqlite")
        process = _run(
            "focustrack_estimator", "--host", "0.0.0.0", "--port", str(port), "--store", store,
            env=env,
        )  # fmt: skip
        try:
            url = f"http://127.0.0.1:{port}"
            _wait_healthy(url, process)
            assert httpx.post(f"{url}/v1/slides", json=slide, headers=headers).status_code == status
        finally:
            process.terminate()
            process.wait(60)


def test_compose_takes_every_token_from_the_env_file() -> None:
    compose = (ROOT / "compose.yaml").read_text()
    example = (ROOT / ".env.example").read_text()
    tokens = set(re.findall(r"\$\{(FOCUSTRACK_\w+_TOKEN)", compose))
    assert tokens == {"FOCUSTRACK_ESTIMATOR_TOKEN", "FOCUSTRACK_FOCUS_TOKEN"}
    for token in tokens:
        assert re.search(rf"^{token}=\S+", example, re.MULTILINE), token
    assert ".env" in (ROOT / ".gitignore").read_text().split()  # secrets stay out of git
