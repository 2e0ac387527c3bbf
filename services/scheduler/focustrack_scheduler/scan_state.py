"""Which scan an output folder holds, ``scan.json``: what a restarted scheduler resumes.

Its entries: ``estimator`` (URL), ``instrument``, ``slide``, ``strategy``, ``params``,
``slide_id`` (the estimator's, once created) and ``tile`` (height, width, channels and
pixel_size_um of the tile images, saved just before the first is kept).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from focustrack_scheduler.outputs import OutputFolderError


class ScanState:
    """The JSON object in the file at `path`, merged into and written whole."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def read(self) -> dict[str, Any] | None:
        """The entries saved so far; None when the folder holds no scan yet.
        OutputFolderError when the file is not a JSON object (damaged, or not a scan's)."""
        if not self.path.exists():
            return None
        try:
            state = json.loads(self.path.read_text())
        except ValueError as error:  # not JSON, or not text
            raise self._damaged(f"it is not JSON ({error})") from error
        if not isinstance(state, dict):
            raise self._damaged(f"it holds a JSON {type(state).__name__}, not an object")
        return state

    def _damaged(self, why: str) -> OutputFolderError:
        return OutputFolderError(
            f"{self.path} is damaged: {why}. It says which estimator slide the folder's scan "
            "resumes: move it away to start the folder afresh, or scan into a new output folder"
        )

    def save(self, **entries: Any) -> None:
        """Merge `entries` into the file (written whole, then renamed: never half a file)."""
        state = {**(self.read() or {}), **entries}
        temporary = self.path.with_name(self.path.name + ".tmp")
        temporary.write_text(json.dumps(state, indent=2) + "\n")
        temporary.replace(self.path)
