"""The scan's event log, ``scan_log.jsonl``: one JSON object per line, flushed as it happens.

Each entry names its ``event`` (acquired, measured, kept, planes; `record.ScanRecord`
writes them). A scheduler killed mid-write leaves the last line cut short: reading the
log back skips it, and every line before it is intact; the next entry starts a line of
its own.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any


class ScanLog:
    """Appends entries to the log at `path` (created if missing); `read` gives them back."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._file = self.path.open("a")
        if self._file.tell() > 0:
            with self.path.open("rb") as file:
                file.seek(-1, 2)
                if file.read(1) != b"\n":  # a line a kill cut short: the next starts anew
                    self._write("\n")

    def read(self) -> Iterator[dict[str, Any]]:
        """Every entry on disk, in order; a line that does not parse (cut short) is skipped."""
        for line in self.path.read_text().splitlines():
            try:
                entry = json.loads(line)
            except ValueError:  # a line cut short by a kill: the rest is intact
                continue
            if isinstance(entry, dict):
                yield entry

    def append(self, entry: dict[str, Any]) -> None:
        """Write `entry` as one line and flush it to the operating system."""
        self._write(json.dumps(entry) + "\n")

    def _write(self, text: str) -> None:
        self._file.write(text)
        self._file.flush()

    def close(self) -> None:
        self._file.close()
