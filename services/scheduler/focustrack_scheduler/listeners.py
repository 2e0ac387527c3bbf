"""Who follows a scan as it happens: callbacks given each entry of its log (the live view)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: A follower of the scan, called with each log entry (`scan_log`) as it is appended.
Listener = Callable[[dict[str, Any]], None]


class Listeners:
    """The observers of one scan's record, called in the order they were added."""

    def __init__(self) -> None:
        self._listeners: list[Listener] = []

    def add(self, listener: Listener) -> None:
        """Call `listener` with every entry from now on."""
        self._listeners.append(listener)

    def notify(self, entry: dict[str, Any]) -> None:
        for listener in self._listeners:
            listener(entry)
