"""The live state of a scan, for the web view: each tile's numbers and what changed since when.

`LiveScan` follows a `ScanRecord` (every entry the scheduler logs: acquisitions,
measurements with the estimator's outcome and the focus curve, images kept) and
keeps, per tile (rows, cols): the focus estimate z_um and its sigma_um (the
estimator's posterior, else the measured best focus), the images acquired, the
flags of the last measurement, whether the tile's image is kept (done) and, with
``--phase``, the spread of its phase (std over the tile, rad).
Every change bumps a version; `changes(since)` gives only the tiles changed
after it, so a 200x200 grid streams a few tiles per update, not 40 000. Pure
apart from a lock: the scheduler's thread writes, the server's event loop reads.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.record import ScanRecord


class LiveScan:
    """One scan's per-tile state (module docstring); heights in um, arrays (rows, cols)."""

    def __init__(self, grid: ScanGrid, label: str = "scan") -> None:
        self.grid = grid
        self.label = label
        self.z_um = np.full(grid.shape, np.nan)
        self.sigma_um = np.full(grid.shape, np.nan)
        self.images = np.zeros(grid.shape, dtype=int)
        self.done = np.zeros(grid.shape, dtype=bool)
        self.phase_std_rad = np.full(grid.shape, np.nan)
        self.flags: dict[tuple[int, int], list[str]] = {}
        self.curve: dict[str, Any] | None = None  # the latest through-focus curve
        self.version = 0
        self.finished = False
        self._changed_at = np.zeros(grid.shape, dtype=np.int64)  # version of each tile's change
        self._lock = threading.Lock()

    @classmethod
    def follow(cls, record: ScanRecord, grid: ScanGrid, label: str = "scan") -> LiveScan:
        """The live state of `record` so far, kept up to date as the scheduler logs more."""
        live = cls(grid, label)
        tally = record.tally
        for entry in tally.acquisitions:
            live.take(entry)
        for entry in tally.measured.values():
            live.take(entry)
        for (row, col), z_um in tally.kept.items():
            live.take({"event": "kept", "row": row, "col": col, "z_um": z_um})
        for entry in tally.phase_stacks:
            live.take(entry)
        record.listeners.add(live.take)
        return live

    def take(self, entry: dict[str, Any]) -> None:
        """Apply one entry of the scan log (`scan_log`)."""
        tile = (entry["row"], entry["col"])
        with self._lock:
            if entry["event"] == "acquired":
                self.images[tile] += entry["n_frames"]
            elif entry["event"] == "measured":
                z_um, sigma_um = entry.get("posterior_um"), entry.get("posterior_sigma_um")
                if z_um is None:
                    z_um, sigma_um = entry["z_um"], entry["sigma_um"]
                self.z_um[tile] = math.nan if z_um is None else z_um
                self.sigma_um[tile] = math.nan if sigma_um is None else sigma_um
                self.flags[tile] = entry["flags"]
                if entry.get("curve_z_um"):
                    self.curve = {
                        "row": tile[0],
                        "col": tile[1],
                        "z_um": entry["curve_z_um"],
                        "scores": entry["curve_scores"],
                        "best_z_um": entry["z_um"],
                        "sigma_um": entry["sigma_um"],
                    }
            elif entry["event"] == "kept":
                self.done[tile] = True
                if not math.isfinite(self.z_um[tile]):  # no measurement: where it was imaged
                    self.z_um[tile] = entry["z_um"]
            elif entry["event"] == "phase":
                spread_rad = entry["phase_std_rad"]
                self.phase_std_rad[tile] = math.nan if spread_rad is None else spread_rad
            else:
                return
            self.version += 1
            self._changed_at[tile] = self.version

    def finish(self) -> None:
        """The scan is over: one last change, so every stream sends `finished`."""
        with self._lock:
            self.finished = True
            self.version += 1

    def changes(self, since: int = 0) -> dict[str, Any]:
        """Plain JSON of the tiles changed after version `since` (all of them for 0).

        `tiles` holds [row, col, z_um, sigma_um, images, done, flags, phase_std_rad] per tile
        (null for NaN, and for a tile without phase).
        """
        with self._lock:
            rows, cols = np.nonzero(self._changed_at > since)
            tiles = [
                [
                    int(row),
                    int(col),
                    _number(self.z_um[row, col]),
                    _number(self.sigma_um[row, col]),
                    int(self.images[row, col]),
                    bool(self.done[row, col]),
                    self.flags.get((int(row), int(col)), []),
                    _number(self.phase_std_rad[row, col]),
                ]
                for row, col in zip(rows, cols, strict=True)
            ]
            return {
                "label": self.label,
                "rows": self.grid.rows,
                "cols": self.grid.cols,
                "version": self.version,
                "since": since,
                "tiles_done": int(self.done.sum()),
                "tiles_total": self.grid.n_tiles,
                # where the tiles are: the map's axes in the stage's micrometres
                "pitch_um": self.grid.pitch_um,
                "origin_x_um": self.grid.origin_x_um,
                "origin_y_um": self.grid.origin_y_um,
                "images": int(self.images.sum()),
                "finished": self.finished,
                "curve": self.curve,
                "tiles": tiles,
            }


def _number(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)
