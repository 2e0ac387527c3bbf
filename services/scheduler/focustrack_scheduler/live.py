"""The live state of a scan, for the web view: each tile's numbers and what changed since when.

`LiveScan` follows a `ScanRecord` (every entry the scheduler logs: acquisitions,
measurements with the estimator's outcome and the focus curve, images kept) and
keeps, per tile (rows, cols): the focus estimate z_um and its sigma_um (the
estimator's posterior, else the measured best focus), the images acquired, the
flags of the last measurement, whether the tile's image is kept (done) and, with
``--phase``, the spread of its phase (std over the tile, rad). Given the depth of field,
it also judges each kept tile in focus or not: against the instrument's truth where there
is one (evaluation; tissue tiles only where the truth says which tiles are empty glass),
else against the focus service's best z for the tile (its last measurement, where that
found one not at an end of the stack); and followed, it keeps a
thumbnail of each kept tile's image at its stage position (`thumbnails.Thumbnails`).
Every change bumps a version; `changes(since)` gives only the tiles changed
after it, so a 200x200 grid streams a few tiles per update, not 40 000. Pure
apart from a lock: the scheduler's thread writes, the server's event loop reads.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from focustrack_core.domain import FocusFlag, kept_in_focus
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.tally import Tile
from focustrack_scheduler.thumbnails import Thumbnails

#: Whose word a tile's in-focus verdict is (`LiveScan.changes`: ``in_focus.by``).
BY_TRUTH, BY_FOCUS_SERVICE = "truth", "focus service"
#: Flags of a best z at an end of the stack: the focus lies beyond, not there.
EDGE_FLAGS = frozenset({FocusFlag.EDGE_LOW.value, FocusFlag.EDGE_HIGH.value})
#: A kept tile's image (h, w, channels) uint8 and its pixel size (um); None if not at hand.
TileImage = Callable[[int, int], tuple[np.ndarray, float] | None]


class LiveScan:
    """One scan's per-tile state (module docstring); heights in um, arrays (rows, cols)."""

    def __init__(
        self,
        grid: ScanGrid,
        label: str = "scan",
        *,
        dof_um: float | None = None,
        truth_um: np.ndarray | None = None,
        empty_glass: np.ndarray | None = None,
        tile_image: TileImage | None = None,
    ) -> None:
        """`dof_um`: the depth of field, to judge tiles in focus (None: not judged);
        `truth_um` (rows, cols): the true focus, evaluation only, and `empty_glass` (rows,
        cols) bool: the truth's tiles without tissue, not judged (None: every tile has some);
        `tile_image`: where a kept tile's image is read for its thumbnail (None: none)."""
        self.grid = grid
        self.label = label
        self.dof_um = dof_um
        self.truth_um = truth_um
        self.empty_glass = empty_glass
        self.thumbnails = Thumbnails(grid)
        self._tile_image = tile_image
        self.z_kept_um = np.full(grid.shape, np.nan)  # the z of each tile's image
        self.planes_um: dict[Tile, list[float]] = {}  # the z of the frames a tile keeps
        self.best_z_um = np.full(grid.shape, np.nan)  # the focus service's, not at an edge
        self.in_focus = np.full(grid.shape, -1, dtype=np.int8)  # 1 yes, 0 no, -1 not judged
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
    def follow(
        cls,
        record: ScanRecord,
        grid: ScanGrid,
        label: str = "scan",
        *,
        dof_um: float | None = None,
        truth_um: np.ndarray | None = None,
        empty_glass: np.ndarray | None = None,
    ) -> LiveScan:
        """The live state of `record` so far, kept up to date as the scheduler logs more,
        with thumbnails of its tiles (read from the record's mosaic as they are kept)."""

        def tile_image(row: int, col: int) -> tuple[np.ndarray, float] | None:
            image = record.mosaic.tile(grid, row, col)
            tile_format = (record.state.read() or {}).get("tile")
            if image is None or tile_format is None:
                return None
            return image, float(tile_format["pixel_size_um"])

        live = cls(
            grid,
            label,
            dof_um=dof_um,
            truth_um=truth_um,
            empty_glass=empty_glass,
            tile_image=tile_image,
        )
        tally = record.tally
        for entry in tally.acquisitions:
            live.take(entry)
        for entry in tally.measured.values():
            live.take(entry)
        for (row, col), z_um in tally.kept.items():
            live.take({"event": "kept", "row": row, "col": col, "z_um": z_um})
        for (row, col), planes_um in tally.planes.items():
            live.take({"event": "planes", "row": row, "col": col, "z_um": planes_um})
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
                at_edge = not EDGE_FLAGS.isdisjoint(entry["flags"])
                best_um = None if at_edge else entry["z_um"]
                self.best_z_um[tile] = math.nan if best_um is None else best_um
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
                self.z_kept_um[tile] = entry["z_um"]
                if not math.isfinite(self.z_um[tile]):  # no measurement: where it was imaged
                    self.z_um[tile] = entry["z_um"]
            elif entry["event"] == "planes":
                self.planes_um[tile] = entry["z_um"]
            elif entry["event"] == "phase":
                spread_rad = entry["phase_std_rad"]
                self.phase_std_rad[tile] = math.nan if spread_rad is None else spread_rad
            else:
                return
            self._judge(tile)
            self.version += 1
            self._changed_at[tile] = self.version
        if entry["event"] in ("kept", "planes"):  # the tile's image is new: its thumbnail
            self._thumbnail(tile)

    def _judge(self, tile: Tile) -> None:
        """Whether `tile`'s kept frames are in focus (module docstring), if it can be said."""
        if self.dof_um is None:
            return
        reference_um = (self.truth_um if self.truth_um is not None else self.best_z_um)[tile]
        glass = self.empty_glass is not None and bool(self.empty_glass[tile])
        if glass or not (math.isfinite(reference_um) and math.isfinite(self.z_kept_um[tile])):
            self.in_focus[tile] = -1  # not kept yet, no tissue, or nothing to judge it by
            return
        kept_um = self.planes_um.get(tile) or [float(self.z_kept_um[tile])]  # planes: with it
        self.in_focus[tile] = kept_in_focus(kept_um, float(reference_um), self.dof_um)

    def _thumbnail(self, tile: Tile) -> None:
        found = None if self._tile_image is None else self._tile_image(*tile)
        if found is None:
            return
        image, pixel_um = found
        self.thumbnails.put(*tile, image, pixel_um)
        with self._lock:  # a change: every stream's next update says the thumbnails moved on
            self.version += 1

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
                "in_focus": self._in_focus_share(),
                # bumped by each new thumbnail: the page then fetches the mosaic again
                "thumbnails_version": self.thumbnails.version,
            }

    def _in_focus_share(self) -> dict[str, Any] | None:
        """Tiles in focus among those judged so far, by whom, and whether only tissue tiles
        are (the truth's empty glass left out); None without a depth of field (not judged)."""
        if self.dof_um is None:
            return None
        return {
            "tiles": int(np.count_nonzero(self.in_focus == 1)),
            "judged": int(np.count_nonzero(self.in_focus >= 0)),
            "by": BY_TRUTH if self.truth_um is not None else BY_FOCUS_SERVICE,
            "tissue_only": self.empty_glass is not None,
        }


def _number(value: float) -> float | None:
    return None if not math.isfinite(value) else float(value)
