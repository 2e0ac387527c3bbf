"""The embedded stack's services end with the process that started them, even when it is
killed by SIGKILL (no `finally` of the demo or a bench runs then)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

#: A process that starts one service (a sleeping Python) as the stack does, says its pid
#: and waits to be killed.
PARENT = """
import sys, time
from pathlib import Path
from focustrack.local_stack import Service
service = Service("sleeper", [sys.executable, "-c", "import time; time.sleep(120)"],
                  Path(sys.argv[1]), ready=lambda: True)
service.start()
print(service.process.pid, flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_a_service_ends_when_the_stack_process_is_killed(tmp_path: Path) -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, str(tmp_path / "sleeper.log")],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert parent.stdout is not None
    child_pid = int(parent.stdout.readline())
    try:
        assert _alive(child_pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline_s = time.monotonic() + 10
        while _alive(child_pid) and time.monotonic() < deadline_s:
            time.sleep(0.05)  # a zombie until its new parent (init) reaps it: gone after
        assert not _alive(child_pid) or _zombie(child_pid)
    finally:
        if _alive(child_pid) and not _zombie(child_pid):
            os.kill(child_pid, signal.SIGKILL)


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1].startswith("Z")
    except (FileNotFoundError, IndexError):
        return False
