"""Helpers for tests of code that runs on other threads (Zenoh's callbacks, servers)."""

from __future__ import annotations

import time
from collections.abc import Callable


def within(condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Whether `condition()` holds within `timeout_s` (s), asked every 50 ms."""
    deadline_s = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline_s:
            return False
        time.sleep(0.05)
    return True
