"""Services start before the router and connect when it appears.

The exploit: `focustrack serve focus` with no router reachable exited after 32 s with a
traceback, and its REST API never came up. Now the focus service's REST API answers at
once (``/healthz`` status ``degraded``), the instrument waits for the bus, and both
join the router when it is started, later, on the endpoint they were given: the focus
service then answers a stack over Zenoh with a tagged result, and the instrument its
info query.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from focustrack.bench.focus import render_stack
from focustrack_core.health import instrument_answers
from focustrack_core.v1 import focus_pb2, instrument_pb2
from focustrack_core.wire import keys
from focustrack_core.wire.codec import PixelPublisher, describe_pixels
from focustrack_core.wire.session import free_port, loopback_endpoint, open_session
from focustrack_core.wire.trust import ResultSigner
from focustrack_estimator.service import spawn

pytestmark = pytest.mark.slow  # services in processes

Z_UM = np.arange(-3.0, 3.01, 0.5)


def wait_until(condition, what: str, process: subprocess.Popen, timeout_s: float = 120) -> None:
    deadline_s = time.monotonic() + timeout_s
    while not condition():
        assert process.poll() is None, f"the service exited while waiting for {what}"
        assert time.monotonic() < deadline_s, f"no {what} after {timeout_s:.0f} s"
        time.sleep(0.2)


def health(http: httpx.Client, port: int) -> dict | None:
    try:
        return http.get(f"http://127.0.0.1:{port}/healthz", timeout=2.0).json()
    except httpx.TransportError:
        return None


def test_focus_and_instrument_start_without_the_router_and_join_it_later(
    http: httpx.Client, tmp_path: Path
) -> None:
    endpoint = loopback_endpoint()  # nothing listens there yet
    port = free_port()
    key_file = tmp_path / "result.key"
    key_file.write_text("k" * 64)
    serve = [sys.executable, "-m", "focustrack", "serve"]
    env = os.environ | {"FOCUSTRACK_FOCUS_RESULT_KEY_FILE": str(key_file)}  # the env twin
    focus = subprocess.Popen(
        [*serve, "focus", "--connect", endpoint, "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    slide = ["--rows", "2", "--cols", "2", "--width", "64", "--height", "64"]
    instrument = subprocess.Popen(
        [*serve, "instrument", "--connect", endpoint, *slide],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_until(lambda: health(http, port) is not None, "REST API", focus)

        def failed_once() -> bool:  # an attempt to reach the router has failed
            return not (health(http, port) or {}).get("zenoh", "").endswith("...")

        wait_until(failed_once, "a failed attempt", focus)
        before = health(http, port)
        assert before is not None and before["status"] == "degraded"
        assert before["zenoh"].startswith("connecting")
        assert before["metrics"]  # the REST part of the health is there too
        assert instrument.poll() is None

        with open_session(listen=[endpoint], mode="router") as router:
            wait_until(
                lambda: (health(http, port) or {}).get("status") == "ok", "connection", focus
            )

            wait_until(
                lambda: instrument_answers(router, "sim"), "instrument on the bus", instrument
            )

            results: queue.Queue = queue.Queue()
            subscriber = router.declare_subscriber(keys.focus_pattern("s1"), results.put)
            header = instrument_pb2.ZStackHeader(
                instrument="sim", slide="s1", row=0, col=0, sequence=3, z_um=Z_UM.tolist(),
                pixel_size_um=0.1, channel_order="L", bit_depth=12,
            )  # fmt: skip
            frames = render_stack("full", 96, Z_UM, -0.4, seed=3)[..., 1][..., None]
            describe_pixels(header, frames)
            publisher = PixelPublisher(router)
            for index, frame in enumerate(frames):
                publisher.put_frame(keys.zframe_key("s1", 0, 0), header, index, frame)
            sample = results.get(timeout=60)
            subscriber.undeclare()
        payload = sample.payload.to_bytes()
        result = focus_pb2.FocusResult.FromString(payload)
        assert result.sequence == 3 and result.HasField("best_z_um")
        signer = ResultSigner.from_file(key_file)
        tag = sample.attachment.to_bytes()
        assert signer.verify(str(sample.key_expr), payload, tag)
        assert not signer.verify(str(sample.key_expr), payload + b"x", tag)
    finally:
        for process in (focus, instrument):
            process.terminate()
        _, focus_log = focus.communicate(timeout=30)
        _, instrument_log = instrument.communicate(timeout=30)
    # SIGTERM: a graceful end, the session closed and the results counted
    assert instrument.returncode == 0 and focus.returncode == 0
    assert "published 1 results" in focus_log
    assert "Traceback" not in focus_log + instrument_log
    assert "still trying" in focus_log  # it said what it waited for


def _ctrl_c_at_its_default() -> None:
    """In the scan's process before it starts: SIGINT at its default, as at a terminal. A
    shell's background job (`make test &` in a script) ignores SIGINT, the test's workers
    and the scan inherit that, and the scan then never heard the test's Ctrl-C (it ran
    into Zenoh's timeout instead: status 1)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize(("stop", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_scan_waiting_for_its_router_stops_at_ctrl_c(
    tmp_path: Path, stop: signal.Signals, status: int
) -> None:
    """Ctrl-C (or SIGTERM: `docker stop`) while `focustrack scan` waits for its router ends
    it at once with its line and status 130 (143). Zenoh waits for a connect endpoint in
    native code, where Python runs no signal handler: the scan used to go on to Zenoh's
    timeout and then end in a traceback; SIGTERM killed it without its line. A socket that
    takes the connection and says nothing stands for the router; the scan's line that it
    waits for one (after 2 s) shows when it is in Zenoh's open. (The socket's first
    connection did not: another test's Zenoh session, still retrying a port of a router
    that had ended, could be first, and the signal then came during the scan's imports.)"""
    with socket.create_server(("127.0.0.1", 0)) as silent:
        port = silent.getsockname()[1]
        command = [
            sys.executable, "-m", "focustrack", "scan", "--no-progress",
            "--estimator", "http://127.0.0.1:9", "--connect", f"tcp/127.0.0.1:{port}",
            "--instrument", "sim", "--slide", "slide-0", "--out", str(tmp_path / "scan"),
        ]  # fmt: skip
        scan = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_ctrl_c_at_its_default,
        )
        assert scan.stderr is not None
        waiting = scan.stderr.readline()  # the end of the file if the scan ended instead
        assert waiting.startswith("focustrack scan: no Zenoh router answers at"), waiting
        scan.send_signal(stop)
        _, err = scan.communicate(timeout=60)
    assert scan.returncode == status, waiting + err
    assert "focustrack scan: interrupted" in err and "Traceback" not in err
    assert not (tmp_path / "scan" / "scan.json").exists()  # nothing was started


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--strategy", "kf-2dd"], "serves no strategy 'kf-2dd'; it serves af-every-tile, "),
        (["--strategy", "kf-wiener0", "--param", "qq=0.2"], "kf-wiener0 has no parameter 'qq'"),
    ],
)
def test_a_strategy_the_estimator_does_not_serve_is_refused_before_the_bus(
    tmp_path: Path, flags: list[str], needle: str
) -> None:
    """A misspelt --strategy or --param was refused only once the router answered (up to
    --bus-timeout-s later): the estimator's list of strategies refuses it first, exit 2.
    A socket that takes connections and says nothing stands for the router: a scan that
    reached for it would say, 2 s on, that no router answers."""
    port = free_port()
    estimator = spawn(tmp_path / "estimator.sqlite", port)
    try:
        with socket.create_server(("127.0.0.1", 0)) as silent:
            command = [
                sys.executable, "-m", "focustrack", "scan", "--no-progress",
                "--estimator", f"http://127.0.0.1:{port}",
                "--connect", f"tcp/127.0.0.1:{silent.getsockname()[1]}",
                "--instrument", "sim", "--slide", "slide-0", "--out", str(tmp_path / "scan"),
                *flags,
            ]  # fmt: skip
            scan = subprocess.run(command, capture_output=True, text=True, timeout=120)
    finally:
        estimator.terminate()
        estimator.wait(timeout=10)
    assert scan.returncode == 2, scan.stderr
    assert needle in scan.stderr and "Traceback" not in scan.stderr
    assert "no Zenoh router answers" not in scan.stderr  # it never reached for the bus
