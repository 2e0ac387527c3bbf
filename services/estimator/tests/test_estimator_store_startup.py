"""The estimator's store at start and stop: a damaged file is refused with its
name, an empty or missing one announced as a new store (a PostgreSQL database too, its
password never said), and SIGTERM closes the store and checkpoints its WAL (real server
processes on loopback)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
from postgres_server import PostgresServer

from focustrack_core.wire.session import free_port
from focustrack_estimator.event_store import Event
from focustrack_estimator.service import spawn
from focustrack_estimator.sqlite_store import SQLiteStore

COMMAND = [sys.executable, "-m", "focustrack_estimator"]


def _filled_store(path: Path, n_slides: int = 40) -> None:
    """A store with enough slides and events to span many pages."""
    store = SQLiteStore(path)
    try:
        for i in range(n_slides):
            store.create_slide(f"slide-{i}", {"strategy": "kf-wiener0", "pad": "x" * 2000})
            event = Event(0, {"a": "y" * 1000}, {"z_um": 1.0}, {"accepted": True})
            store.append(f"slide-{i}", event, accepted=True, done=False)
    finally:
        store.close()


def test_a_store_damaged_mid_file_is_refused_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "damaged.sqlite"
    _filled_store(path)
    data = bytearray(path.read_bytes())
    assert len(data) > 40 * 4096
    middle = len(data) // 2
    data[middle : middle + 8192] = b"\xa5" * 8192  # two pages in the middle overwritten
    path.write_bytes(bytes(data))
    started = subprocess.run(
        [*COMMAND, "--port", str(free_port()), "--store", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert started.returncode == 2, started.stderr
    assert str(path) in started.stderr and "damaged" in started.stderr
    assert "Traceback" not in started.stderr


def test_a_file_that_is_not_sqlite_is_refused_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "notes.sqlite"
    path.write_bytes(b"these are not the slides you are looking for\n" * 100)
    started = subprocess.run(
        [*COMMAND, "--port", str(free_port()), "--store", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert started.returncode == 2 and str(path) in started.stderr, started.stderr
    assert "Traceback" not in started.stderr


def _start_and_stop(http: httpx.Client, store: Path | str) -> tuple[int, str, str]:
    """Start the service on `store`, create a slide, SIGTERM it; (exit code, its stdout, its
    stderr)."""
    port = free_port()
    process = subprocess.Popen(
        [*COMMAND, "--port", str(port), "--store", str(store)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        url = f"http://127.0.0.1:{port}"
        for _ in range(1200):
            try:
                if http.get(f"{url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                if process.poll() is not None:
                    break
                time.sleep(0.1)
        body = {"strategy": "kf-wiener0", "grid": {"rows": 3, "cols": 3}}
        assert http.post(f"{url}/v1/slides", json=body, timeout=60).status_code == 201
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert "Traceback" not in err, err
    return process.returncode, out, err


def test_an_empty_or_missing_store_is_announced_as_new(http: httpx.Client, tmp_path: Path) -> None:
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    for path in (empty, tmp_path / "missing.sqlite"):
        code, out, _ = _start_and_stop(http, path)
        assert code == 0 and f"creating a new store at {path}" in out, out
    code, out, _ = _start_and_stop(http, empty)  # now it holds a slide: no longer new
    assert code == 0 and "creating a new store" not in out
    store = SQLiteStore(empty)
    assert store.count_slides() == 2
    store.close()


def test_a_database_is_announced_by_its_address_never_its_password(
    http: httpx.Client,
    postgres: PostgresServer,
) -> None:
    password = "never-in-the-log-8e2f"  # the test server trusts loopback: any password logs in
    url = postgres.new_database()
    with_password = url.replace("postgres@", f"postgres:{password}@", 1)
    address = url.removeprefix("postgresql://")
    for new in (True, False):
        code, out, err = _start_and_stop(http, with_password)
        assert code == 0, err
        assert password not in out + err
        assert f"store postgresql://{address}," in out, out
        assert ("created the estimator's tables" in out) is new, out
        assert "file" not in out, out


def test_sigterm_closes_the_store_and_checkpoints_its_wal(
    http: httpx.Client, tmp_path: Path
) -> None:
    path = tmp_path / "estimator.sqlite"
    port = free_port()
    process = spawn(path, port, timeout_s=120)
    url = f"http://127.0.0.1:{port}/v1/slides"
    slide = http.post(
        url, json={"strategy": "kf-2d", "grid": {"rows": 4, "cols": 4}}, timeout=60
    ).json()
    for _ in range(3):
        pending = http.get(f"{url}/{slide['id']}/next").json()
        measurement = {
            "row": pending["row"],
            "col": pending["col"],
            "sequence": pending["sequence"],
        }
        response = http.post(f"{url}/{slide['id']}/measurements", json={**measurement, "z_um": 1})
        assert response.status_code == 200
    wal = Path(f"{path}-wal")
    assert wal.exists()
    process.send_signal(signal.SIGTERM)
    assert process.wait(60) == 0  # not -15: the service shut down and closed its store
    assert not wal.exists() or wal.stat().st_size == 0
    store = SQLiteStore(path)
    try:
        assert store.slide(slide["id"]).n_events == 3  # type: ignore[union-attr]
        assert store.snapshot(slide["id"]) is not None  # taken at shutdown
    finally:
        store.close()
