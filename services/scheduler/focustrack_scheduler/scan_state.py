"""Which scan an output folder holds, ``scan.json``: what a restarted scheduler resumes.

Its entries: ``estimator`` (URL), ``instrument``, ``slide``, ``strategy``, ``params``,
``slide_id`` (the estimator's, once created) and ``tile`` (height, width, channels and
pixel_size_um of the tile images, saved just before the first is kept).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class ScanState:
    """The JSON object in the file at `path`, merged into and written whole."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def read(self) -> dict[str, Any] | None:
        """The entries saved so far; None when the folder holds no scan yet."""
        return json.loads(self.path.read_text()) if self.path.exists() else None

    def save(self, **entries: Any) -> None:
        """Merge `entries` into the file (written whole, then renamed: never half a file)."""
        state = {**(self.read() or {}), **entries}
        temporary = self.path.with_name(self.path.name + ".tmp")
        temporary.write_text(json.dumps(state, indent=2) + "\n")
        temporary.replace(self.path)
