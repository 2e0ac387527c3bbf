"""The durable record of one scan in its output folder, as the engine writes it.

A `ScanRecord` holds the parts, each of one concern: the folder's scan state
(`scan_state.ScanState`, ``scan.json``), the event log (`scan_log.ScanLog`), what the log
says so far (`tally.ScanTally`), the mosaic being filled in and the planes
(`mosaic_store.MosaicStore`), and who follows the scan (`listeners.Listeners`). Opened on
a folder that holds an earlier run, it reads the log back, so the scan carries on.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from focustrack_core.domain import Acquisition, Measurement, Outcome
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import finite_or_none
from focustrack_scheduler.listeners import Listeners
from focustrack_scheduler.mosaic_store import MosaicStore
from focustrack_scheduler.outputs import LOG_FILE, STATE_FILE
from focustrack_scheduler.scan_log import ScanLog
from focustrack_scheduler.scan_state import ScanState
from focustrack_scheduler.tally import ScanTally


class ScanRecord:
    """The record of the scan in `out_dir` (created if missing); see the module docstring."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.state = ScanState(self.out_dir / STATE_FILE)
        self.log = ScanLog(self.out_dir / LOG_FILE)
        self.tally = ScanTally()
        for entry in self.log.read():
            with contextlib.suppress(KeyError):  # an entry this version cannot read
                self.tally.take(entry)
        self.mosaic = MosaicStore(self.out_dir)
        #: Called with every entry appended from now on (the live view follows the scan).
        self.listeners = Listeners()

    def _append(self, entry: dict[str, Any]) -> None:
        self.log.append(entry)
        self.tally.take(entry)
        self.listeners.notify(entry)

    def acquired(self, acquisition: Acquisition, n_frames: int, scan_time_s: float) -> None:
        """An acquisition was made: `n_frames` images, `scan_time_s` simulated seconds."""
        self._append(
            {
                "event": "acquired",
                "row": acquisition.row,
                "col": acquisition.col,
                "sequence": acquisition.index,
                "purpose": acquisition.purpose.value,
                "n_frames": n_frames,
                "scan_time_s": scan_time_s,
            }
        )

    def measurement(
        self,
        acquisition: Acquisition,
        measurement: Measurement,
        outcome: Outcome,
        curve: tuple[list[float], list[float]] | None,
    ) -> None:
        """The best focus found in `acquisition`'s stack was posted (z and sigma in um).

        `outcome` is what it did to the tile's estimate; `curve` the stack's focus curve
        (z of every frame in um, its scores), where the focus service sent one.
        """
        self._append(
            {
                "event": "measured",
                "row": acquisition.row,
                "col": acquisition.col,
                "sequence": acquisition.index,
                "measure": acquisition.measure,  # False: an image-only acquisition's post
                "z_um": measurement.z_um,
                "sigma_um": measurement.sigma_um,
                "flags": sorted(str(flag) for flag in measurement.flags),
                "posterior_um": finite_or_none(outcome.posterior_um),
                "posterior_sigma_um": finite_or_none(outcome.posterior_sigma_um),
                "curve_z_um": None if curve is None else curve[0],
                "curve_scores": None if curve is None else curve[1],
                # where the first-frame check found the tile's one frame out of focus
                **({"frame_out_of_focus": True} if measurement.frame_out_of_focus else {}),
            }
        )

    def retaken(self, row: int, col: int, sequence: int, scan_time_s: float) -> None:
        """Tile (row, col) was taken again, one frame, at a second pass's lateral offset."""
        self._append(
            {
                "event": "acquired",
                "row": row,
                "col": col,
                "sequence": sequence,
                "purpose": "retake",
                "n_frames": 1,
                "scan_time_s": scan_time_s,
            }
        )

    def keep(
        self,
        grid: ScanGrid,
        row: int,
        col: int,
        z_um: float,
        image: np.ndarray,
        bit_depth: int,
        stage_um: tuple[float, float] | None = None,
    ) -> None:
        """Tile (row, col)'s image (h, w, channels) at `z_um` goes into the mosaic; the stage
        stood at `stage_um` (x, y) for it, where the instrument says."""
        self.mosaic.write_tile(grid, row, col, image, bit_depth)
        entry: dict[str, Any] = {"event": "kept", "row": row, "col": col, "z_um": z_um}
        if stage_um is not None:
            entry["stage_x_um"], entry["stage_y_um"] = stage_um
        self._append(entry)

    def keep_planes(
        self,
        grid: ScanGrid,
        row: int,
        col: int,
        z_um: list[float],
        frames: np.ndarray,
        bit_depth: int,
    ) -> None:
        """Tile (row, col) keeps `frames` (n, h, w, channels) at `z_um` (n,), ascending; its
        mosaic tile becomes their fusion, each pixel from the sharpest (`fuse_planes`)."""
        file = self.mosaic.save_planes(grid, row, col, frames, bit_depth)
        self._append({"event": "planes", "row": row, "col": col, "z_um": z_um, "file": file})

    def phase(
        self,
        grid: ScanGrid,
        row: int,
        col: int,
        *,
        sequence: int,
        n_frames: int,
        scan_time_s: float,
        reference_z_um: float,
        field: np.ndarray | None,
        background_share: float | None,
        error: str | None,
    ) -> None:
        """A phase stack of tile (row, col) was taken (`n_frames` images, `scan_time_s`
        simulated seconds) for the plane at `reference_z_um`; its `field`, float32 (2, h, w):
        the phase (rad) and amplitude, is kept, with the share of the tile the phase
        service took as glass (zero phase), or `error` says why there is none."""
        file = None if field is None else self.mosaic.save_phase(row, col, field)
        spread_rad = None if field is None else finite_or_none(float(np.std(field[0])))
        self._append(
            {
                "event": "phase",
                "row": row,
                "col": col,
                "sequence": sequence,
                "n_frames": n_frames,
                "scan_time_s": scan_time_s,
                "reference_z_um": reference_z_um,
                "file": file,
                "phase_std_rad": spread_rad,
                "background_share": background_share,
                "error": error,
            }
        )

    def close(self) -> None:
        self.log.close()
        self.mosaic.close()
