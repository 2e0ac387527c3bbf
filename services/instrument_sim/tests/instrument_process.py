"""The simulator as a process of its own, for the tests that start its command."""

from __future__ import annotations

import subprocess
import time

import zenoh

from focustrack_core import health


def wait_until_it_answers(client: zenoh.Session, name: str, process: subprocess.Popen) -> None:
    """Return once instrument `name` answers on `client` (within about 20 s); fail with the
    process's error output if it exits first, or if it never answers."""
    for _ in range(100):
        if health.instrument_answers(client, name):
            return
        assert process.poll() is None, process.stderr.read() if process.stderr else ""
        time.sleep(0.2)
    raise AssertionError(f"instrument {name!r} did not answer")
