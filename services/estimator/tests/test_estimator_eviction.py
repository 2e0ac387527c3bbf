"""Idle slides leave memory : least recently used slides are evicted beyond the
configured count or bytes, reload from the store on their next request as if never gone,
and a deleted slide's memory goes back to the system (real server processes on loopback)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import httpx

from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn


def _live_slides(http: httpx.Client, url: str) -> int:
    text = http.get(f"{url}/metrics").text
    match = re.search(r"^\w+_live_slides (\d+)", text, re.MULTILINE)
    assert match, text
    return int(match[1])


def _rss_bytes(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    match = re.search(r"^VmRSS:\s+(\d+) kB", status, re.MULTILINE)
    assert match
    return int(match[1]) * 1024


def _measure(http: httpx.Client, url: str, slide_id: str, n: int) -> list[dict[str, Any]]:
    """`n` measurements of a slide (a tilted plane), the outcomes in order."""
    outcomes = []
    for _ in range(n):
        pending = http.get(f"{url}/v1/slides/{slide_id}/next").json()
        body = {
            "row": pending["row"],
            "col": pending["col"],
            "sequence": pending["sequence"],
            "z_um": 0.1 * pending["col"] + 0.05 * pending["row"],
        }
        response = http.post(f"{url}/v1/slides/{slide_id}/measurements", json=body)
        assert response.status_code == 200, response.text
        outcomes.append(response.json())
    return outcomes


def test_idle_slides_are_evicted_and_reload_as_if_never_gone(
    http: httpx.Client, tmp_path: Path
) -> None:
    port = free_port()
    options = ["--max-live-slides", "2", "--snapshot-every", "3"]
    process = spawn(tmp_path / "evict.sqlite", port, timeout_s=120, options=options)
    url = f"http://127.0.0.1:{port}"
    try:
        body = {"strategy": "kf-2d", "grid": {"rows": 5, "cols": 6}}
        ids = [http.post(f"{url}/v1/slides", json=body, timeout=60).json()["id"] for _ in range(4)]
        assert _live_slides(http, url) == 2
        # The first slide, long evicted, continues where it was; an identical slide that
        # stays in memory throughout gives the same outcomes, number for number.
        first = _measure(http, url, ids[0], 4)  # evicted and reloaded at each of these turns
        for other in ids[2:]:
            _measure(http, url, other, 2)
        first += _measure(http, url, ids[0], 4)  # reloaded again (from its snapshot after 3)
        assert _live_slides(http, url) == 2
        reference = http.post(f"{url}/v1/slides", json=body).json()["id"]
        assert _measure(http, url, reference, 8) == first
        assert http.get(f"{url}/v1/slides/{ids[0]}").json()["n_acquisitions"] == 8
    finally:
        process.terminate()
        process.wait(60)


def test_evicted_by_bytes_and_a_deleted_slides_memory_is_released(
    http: httpx.Client, tmp_path: Path
) -> None:
    port = free_port()
    # Room for one wide slide in memory: 18 covariances of 603^2 floats each (52 MB).
    options = ["--max-live-bytes", str(400 * 2**20)]
    process = spawn(tmp_path / "bytes.sqlite", port, timeout_s=120, options=options)
    url = f"http://127.0.0.1:{port}"
    try:
        # The strategies are imported with the first slide: a small one comes and goes first.
        small = {"strategy": "kf-2d", "grid": {"rows": 2, "cols": 2}}
        small_id = http.post(f"{url}/v1/slides", json=small, timeout=120).json()["id"]
        assert http.delete(f"{url}/v1/slides/{small_id}").status_code == 204
        body = {"strategy": "kf-2d", "grid": {"rows": 4, "cols": 300}}
        baseline = _rss_bytes(process.pid)
        first = http.post(f"{url}/v1/slides", json=body, timeout=120).json()["id"]
        with_one = _rss_bytes(process.pid)
        assert with_one - baseline > 50 * 2**20  # the slide is really in memory
        second = http.post(f"{url}/v1/slides", json=body, timeout=120).json()["id"]
        assert _live_slides(http, url) == 1  # the first was evicted to make room
        assert _rss_bytes(process.pid) < with_one + 40 * 2**20  # and its memory reused
        assert http.delete(f"{url}/v1/slides/{second}").status_code == 204
        assert _live_slides(http, url) == 0
        assert _rss_bytes(process.pid) < baseline + 40 * 2**20  # given back to the system
        assert http.get(f"{url}/v1/slides/{first}/next", timeout=120).status_code == 200
    finally:
        process.terminate()
        process.wait(60)
