"""What a scan has done so far, folded from its log's entries (`scan_log.ScanLog`).

The same entries build it during the scan and, read back, after a restart: acquisitions
(images and simulated seconds), the last measurement of each tile, the z of each tile's
kept image and of the frames a tile keeps besides (its planes), and the phase stacks
(with ``--phase``: images, seconds, and the file of each tile's phase).
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from focustrack_core.geometry import ScanGrid

#: A tile of the grid: (row, col).
Tile = tuple[int, int]


class ScanTally:
    """The log's entries by kind (heights in um); `take` folds in one more."""

    def __init__(self) -> None:
        self.acquisitions: list[dict[str, Any]] = []
        self.kept: dict[Tile, float] = {}  # tile -> z (um) of its image
        self.planes: dict[Tile, list[float]] = {}  # tile -> z (um) of its frames
        self.measured: dict[Tile, dict[str, Any]] = {}  # tile -> its last measurement
        #: tile -> its last measurement of a stack that was measured: an image-only
        #: acquisition (one frame at a sure prediction, more frames to keep) posts none
        self.focus_measured: dict[Tile, dict[str, Any]] = {}
        self.phase_stacks: list[dict[str, Any]] = []  # every phase stack taken
        self.phase: dict[Tile, str] = {}  # tile -> the file of its phase (where it has one)

    def take(self, entry: dict[str, Any]) -> None:
        """Fold in one log entry (KeyError if it lacks its event's fields)."""
        event = entry["event"]
        if event == "acquired":
            self.acquisitions.append(entry)
        elif event == "kept":
            self.kept[(entry["row"], entry["col"])] = entry["z_um"]
        elif event == "planes":
            self.planes[(entry["row"], entry["col"])] = entry["z_um"]
        elif event == "measured":
            self.measured[(entry["row"], entry["col"])] = entry
            if entry.get("measure", True):  # logs before the field: every entry
                self.focus_measured[(entry["row"], entry["col"])] = entry
        elif event == "phase":
            self.phase_stacks.append(entry)
            if entry["file"] is not None:
                self.phase[(entry["row"], entry["col"])] = entry["file"]

    @property
    def n_images(self) -> int:
        return sum(entry["n_frames"] for entry in self.acquisitions)

    @property
    def scan_time_s(self) -> float:
        return float(sum(entry["scan_time_s"] for entry in self.acquisitions))

    @property
    def frames_kept(self) -> int:
        """Frames kept over all tiles (one per tile, all of its planes where it keeps some)."""
        return len(self.kept) + sum(len(z_um) - 1 for z_um in self.planes.values())

    def flag_counts(self) -> dict[str, int]:
        """How many tiles' last measured stack carries each flag (flags none carries: absent)."""
        counts = Counter(flag for entry in self.focus_measured.values() for flag in entry["flags"])
        return dict(sorted(counts.items()))

    def tiles_without_focus(self) -> list[Tile]:
        """The tiles whose stacks found no focus (the last stack measured has no z: a flat
        or empty stack), row-major. A tile only imaged, at a sure prediction, is not one."""
        return sorted(tile for tile, entry in self.focus_measured.items() if entry["z_um"] is None)

    def tiles_found_empty(self) -> set[Tile]:
        """The tiles whose last stack or look found nothing in view (flagged `empty`; a
        phase scan reads a frame only imaged as a look)."""
        return {tile for tile, entry in self.measured.items() if "empty" in entry["flags"]}

    def images_per_tile(self, grid: ScanGrid) -> np.ndarray:
        """Images acquired on each tile, (rows, cols)."""
        counts = np.zeros(grid.shape, dtype=int)
        for entry in self.acquisitions:
            counts[entry["row"], entry["col"]] += entry["n_frames"]
        return counts

    def z_kept_um(self, grid: ScanGrid) -> np.ndarray:
        """The z of each tile's image, (rows, cols) in um; NaN where none was kept."""
        z_um = np.full(grid.shape, np.nan)
        for (row, col), z in self.kept.items():
            z_um[row, col] = z
        return z_um
