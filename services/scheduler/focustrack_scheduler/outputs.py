"""What a scan leaves in its output folder: the files' names, the mosaic's formats, wall time.

During the scan (the record, `record.ScanRecord`, and its parts):
- ``scan.json``: which scan this folder holds (estimator URL and slide id, instrument,
  slide, strategy; the tile format once known), written when the slide is created
  (`scan_state.ScanState`);
- ``scan_log.jsonl``: one line per acquisition made (tile, frames, simulated seconds),
  per measurement posted (tile, best z, sigma, flags), per tile image kept (tile, z) and
  per tile that keeps several frames (tile, their z), appended and flushed as they happen
  (`scan_log.ScanLog`);
- ``mosaic.partial.npy``: the mosaic being filled in, a memory map on disk;
- ``planes/r{row}_c{col}.npy``: the frames a tile keeps where one is too unsure to be in
  focus (`Outcome.planes_um`), (n, h, w, channels) as the camera gave them, ascending in z;
  the tile's image in the mosaic is then their fusion (`fusion.fuse_planes`);
- ``phase/r{row}_c{col}.npy`` (with ``--phase``): a tile's phase and amplitude, float32
  (2, h, w), as the phase service reconstructed them at the z of its image
  (all `mosaic_store.MosaicStore`).
A scheduler that is restarted on the same folder reads these back and carries on.

At the end, each by its writer (`writers.DEFAULT_WRITERS`, run on a `finished.FinishedScan`):
- ``focus_map.csv`` / ``focus_map.npy``: every layer of the estimator's map (prior,
  posterior and smoothed heights with their sigma, z used), as the estimator exports them;
- ``scan.png``: true surface, estimated map, error map, images per tile;
- the in-focus tile images side by side (8-bit RGB, with a pyramid) for a slide viewer:
  ``mosaic.ome.zarr`` (OME-Zarr, NGFF 0.5: the default; each tile's best z, sigma and flags
  in its attributes, the focus-map layers as arrays beside it, and with ``--phase`` the
  phase in radians as an image of its own over the mosaic, ``phase``, and the frames an
  uncertain tile keeps as images of their own, ``planes``; where tiles overlap, a virtual
  slide's, the tiles stitched at their stage positions, `stitch`, and every image placed
  in the stage's micrometres) or ``mosaic.ome.tif``
  (`MosaicFormat`), and ``mosaic.png``, a small preview;
- ``report.json``: images acquired, simulated scan time, in-focus fraction and MAE against
  the instrument's truth, and the wall-time split (`report.scan_report`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import StrEnum


class OutputFolderError(ValueError):
    """What an output folder holds from an earlier run cannot be carried on: damaged, or
    made for another grid or tile size. The message says which file and what to do."""


STATE_FILE = "scan.json"
LOG_FILE = "scan_log.jsonl"
#: Held (an advisory lock, with the holder's process id) while a scan runs in the folder.
LOCK_FILE = "scan.lock"
PARTIAL_MOSAIC = "mosaic.partial.npy"
MOSAIC = "mosaic.ome.tif"
MOSAIC_ZARR = "mosaic.ome.zarr"
MOSAIC_PREVIEW = "mosaic.png"
REPORT = "report.json"
PLOTS = "scan.png"
FOCUS_MAP_CSV = "focus_map.csv"
FOCUS_MAP_NPY = "focus_map.npy"
PLANES = "planes"
PHASE = "phase"
#: Every file a scan writes in its output folder.
SCAN_FILES = (
    STATE_FILE,
    LOG_FILE,
    LOCK_FILE,
    PARTIAL_MOSAIC,
    MOSAIC,
    MOSAIC_ZARR,
    MOSAIC_PREVIEW,
    REPORT,
    PLOTS,
    FOCUS_MAP_CSV,
    FOCUS_MAP_NPY,
    PLANES,
    PHASE,
)
#: Group of the OME-Zarr mosaic that holds the focus-map layers, one NGFF image each.
ZARR_MAPS = "maps"
#: Group of the OME-Zarr mosaic that holds the phase (rad), an NGFF image over the mosaic.
ZARR_PHASE = "phase"
#: Group of the OME-Zarr mosaic that holds the frames uncertain tiles keep, an NGFF image
#: (c, z, y, x) each (``r{row}_c{col}``), their z in its attributes.
ZARR_PLANES = "planes"
#: Key of FocusTrack's own attributes in the OME-Zarr root
#: (`finished.FinishedScan.tile_metadata`).
ZARR_ATTRS = "focustrack"


class MosaicFormat(StrEnum):
    """The file the mosaic of a scan is written as."""

    OME_ZARR = "ome-zarr"  # mosaic.ome.zarr: NGFF 0.5, lazy in napari and the OME viewers
    OME_TIFF = "ome-tiff"  # mosaic.ome.tif: a tiled pyramid for QuPath and slide viewers

    @property
    def file_name(self) -> str:
        return MOSAIC_ZARR if self is MosaicFormat.OME_ZARR else MOSAIC


#: The scan state's entry of the wall-time split of the scan's runs so far (`WallTimes`).
WALL_STATE_KEY = "wall_time_s"
#: The scan state's entry of the stitched mosaic's seam error (px), for a finished scan
#: run again, whose mosaic is no longer in tiles to place.
SEAM_STATE_KEY = "seam_error_px"


@dataclass
class WallTimes:
    """Where the scan's wall-clock seconds went, as the scheduler saw them (they add up to total).

    - rendering: acquire request sent -> stack published (the instrument rendering it);
    - transport: stack published -> acquire reply and stack both received;
    - focus_computation: the focus service's own compute time of the stacks awaited;
    - estimation: the estimator's HTTP calls (next, measurements, slide creation);
    - waiting: the rest of the wait for focus results (their queueing and travel);
    - phase: phase stacks (with ``--phase``): acquired, their results awaited and kept;
    - scheduler: everything else (tile images, the log, the progress display).
    """

    rendering_s: float = 0.0
    transport_s: float = 0.0
    focus_computation_s: float = 0.0
    estimation_s: float = 0.0
    waiting_s: float = 0.0
    phase_s: float = 0.0
    scheduler_s: float = 0.0
    total_s: float = 0.0

    def close(self, total_s: float) -> None:
        """Set the total; what no other part accounts for is the scheduler's own."""
        self.total_s = total_s
        parts = (self.rendering_s, self.transport_s, self.focus_computation_s)
        waits = self.estimation_s + self.waiting_s + self.phase_s
        self.scheduler_s = max(0.0, total_s - sum(parts) - waits)

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def of_dict(cls, saved: object) -> WallTimes:
        """The split `as_dict` gave (a scan state's entry): every part it has that is a
        number; none (an older state, another tool's) is zero."""
        saved = saved if isinstance(saved, dict) else {}
        return cls(
            **{
                f.name: float(saved[f.name])
                for f in fields(cls)
                if isinstance(saved.get(f.name), int | float)
            }
        )

    def plus(self, other: WallTimes) -> WallTimes:
        """The split of two runs of one scan (a scan interrupted and resumed), part by part."""
        return WallTimes(
            **{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)}
        )
