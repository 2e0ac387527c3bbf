"""Faults end well: a scan rides out a router restart, and the demo's stack restarts a child.

The exploit: a scan gave up after 3 tries 1 s apart, so a 5 s router restart ended it.
Now the engine retries with exponential back-off for up to a minute, and Zenoh client
sessions reconnect to the restarted router by themselves: a scan whose router is down
for 8 s mid-scan completes, every tile imaged, nothing lost. And `focustrack demo`'s
stack starts again a service that died, saying so.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from focustrack.local_stack import LocalStack
from focustrack_scheduler import outputs

pytestmark = pytest.mark.slow  # services in processes

ROWS = COLS = 4
SIZE = 128
INSTRUMENT_ARGS = [
    "--seed", "5", "--rows", str(ROWS), "--cols", str(COLS),
    "--width", str(SIZE), "--height", str(SIZE),
]  # fmt: skip
ROUTER_DOWN_S = 8.0  # longer than the 5 s restart that used to end a scan


def acquisitions_logged(out_dir: Path) -> int:
    path = out_dir / outputs.LOG_FILE
    return path.read_text().count('"event": "acquired"') if path.exists() else 0


def test_a_scan_rides_out_a_router_restart(http: httpx.Client, tmp_path: Path) -> None:
    with LocalStack(tmp_path / "stack", INSTRUMENT_ARGS, router_process=True) as stack:
        out_dir = tmp_path / "scan"
        command = [
            sys.executable, "-m", "focustrack", "scan", "--no-progress",
            "--estimator", stack.estimator_url, "--connect", stack.endpoint,
            "--result-key-file", str(stack.result_key_file),
            "--focus-timeout-s", "5", "--instrument-timeout-s", "10", "--out", str(out_dir),
        ]  # fmt: skip
        scan = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=os.environ | {"PYTHONUNBUFFERED": "1"},
        )
        deadline_s = time.monotonic() + 120
        while acquisitions_logged(out_dir) < 4:
            assert scan.poll() is None, scan.communicate()
            assert time.monotonic() < deadline_s, "the scan made no progress"
            time.sleep(0.05)
        stack.services["router"].kill()
        time.sleep(ROUTER_DOWN_S)
        assert scan.poll() is None  # still waiting for the bus, not given up
        stack.restart("router")
        _, stderr = scan.communicate(timeout=240)
        assert scan.returncode == 0, stderr
        report = json.loads((out_dir / outputs.REPORT).read_text())
        assert report["tiles_imaged"] == ROWS * COLS
        slide = http.get(f"{stack.estimator_url}/v1/slides/{report['estimator_slide_id']}")
        assert slide.json()["done"] is True
        logged = [
            json.loads(line) for line in (out_dir / outputs.LOG_FILE).read_text().splitlines()
        ]
        measured = {entry["sequence"] for entry in logged if entry["event"] == "measured"}
        assert len(measured) == slide.json()["n_acquisitions"]  # none lost
        assert "retrying" in stderr  # it waited, with back-off, and said so


def test_the_demo_stack_restarts_a_service_that_died(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    with LocalStack(tmp_path, INSTRUMENT_ARGS, supervise=True) as stack:
        first = stack.services["estimator"].process
        assert first is not None
        first.kill()
        deadline_s = time.monotonic() + 120
        while not (stack.restarts["estimator"] == 1 and stack.services["estimator"].ready()):
            assert time.monotonic() < deadline_s, "the estimator was not started again"
            time.sleep(0.2)
        assert stack.services["estimator"].process is not first
        assert stack.restarts == {"instrument": 0, "focus": 0, "estimator": 1}
    assert "estimator exited with status -9; starting it again" in capfd.readouterr().err
