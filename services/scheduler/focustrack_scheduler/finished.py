"""A finished scan as its output writers see it, and the writers' interface.

`FinishedScan.of` takes what the record, the estimator and the instrument know at the end
of a scan into one value that no longer changes; each `OutputWriter` writes one output of
it (`writers.DEFAULT_WRITERS`: the focus map, the plots, the mosaic and its preview, the
OME-Zarr metadata, the phase, the report). Adding an output is adding a writer to the list a scan is
given (`scan.ScanJob.writers`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import finite_or_none, map_layers
from focustrack_scheduler.outputs import (
    PARTIAL_MOSAIC,
    SEAM_STATE_KEY,
    STATE_FILE,
    MosaicFormat,
    WallTimes,
)
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.report import scan_report
from focustrack_scheduler.scan_state import ScanState
from focustrack_scheduler.stitch import (
    Placement,
    compose,
    overlapping,
    place_tiles,
    tiles_of_mosaic,
)
from focustrack_scheduler.tally import Tile

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FinishedScan:
    """Everything an output writer may read of a finished scan (heights in um).

    `state` is the folder's scan.json (estimator, instrument, slide, strategy, params,
    slide_id, and `tile`: the tile images' height, width, channels and pixel_size_um);
    `kept` the z of each tile's image, `planes` the z of the frames a tile keeps besides,
    `measured` each tile's last measurement of a measured stack as logged (not an
    image-only acquisition's); `images_per_tile` (rows, cols);
    `mosaic` the kept images side by side, (rows * h, cols * w, channels) uint8, read-only
    (None when no tile was kept); `report` the figures of ``report.json``; `phase` the
    file (relative to `out_dir`) of each tile's phase and amplitude, float32 (2, h, w),
    where it has one (``--phase``; none by default).
    """

    out_dir: Path
    grid: ScanGrid
    dof_um: float
    focus_map: FocusMap
    truth_um: np.ndarray | None  # the instrument's truth (evaluation only), if it has one
    state: Mapping[str, Any]
    kept: Mapping[Tile, float]
    planes: Mapping[Tile, tuple[float, ...]]
    measured: Mapping[Tile, Mapping[str, Any]]
    images_per_tile: np.ndarray
    mosaic: np.ndarray | None
    mosaic_format: MosaicFormat
    report: Mapping[str, Any]
    phase: Mapping[Tile, str] = field(default_factory=lambda: MappingProxyType({}))
    #: where the kept tiles lie, stitched by the stage and their overlaps, where tiles
    #: overlap (a virtual slide's); None: side by side, as in `mosaic`
    placement: Placement | None = None

    @classmethod
    def of(
        cls,
        record: ScanRecord,
        grid: ScanGrid,
        focus_map: FocusMap,
        truth_um: np.ndarray | None,
        dof_um: float,
        wall: WallTimes,
        mosaic_format: MosaicFormat,
        focus_results_rejected: int = 0,
    ) -> FinishedScan:
        """The scan `record` holds, on `grid`, with the estimator's `focus_map`, the
        instrument's `truth_um` (rows, cols) and depth of field, its wall-time split, the
        mosaic's format and the focus results rejected for want of a trusted tag."""
        state = record.state.read() or {}
        tally = record.tally
        mosaic = record.mosaic.read() if "tile" in state else None
        mosaic_file = mosaic_format.file_name if mosaic is not None else None
        if mosaic is None:  # a finished scan run again: its mosaic was written before
            names = dict.fromkeys(f.file_name for f in (mosaic_format, *MosaicFormat))
            mosaic_file = next((n for n in names if (record.out_dir / n).exists()), None)
            if mosaic_file not in (None, mosaic_format.file_name):
                log.warning(
                    "the scan in %s was finished before, its mosaic written as %s: it cannot "
                    "be written again as %s (the tiles' images are in the mosaic alone)",
                    record.out_dir, mosaic_file, mosaic_format.file_name,
                )  # fmt: skip
        images_per_tile = tally.images_per_tile(grid)
        images_per_tile.setflags(write=False)
        placement = None
        if mosaic is not None:
            tile = state["tile"]
            pixel_um = float(tile["pixel_size_um"])
            if overlapping(grid, int(tile["width"]), pixel_um):
                placement = place_tiles(tiles_of_mosaic(mosaic, grid, tally.kept), grid, pixel_um)
        report = scan_report(
            tally,
            state,
            grid,
            focus_map,
            truth_um,
            dof_um,
            wall.as_dict(),
            focus_results_rejected,
            mosaic_file,
        )
        if placement is not None:
            report["seam_error_px"] = placement.seam_error_px
        elif mosaic is None and SEAM_STATE_KEY in state:  # a finished scan run again
            report["seam_error_px"] = state[SEAM_STATE_KEY]
        return cls(
            out_dir=record.out_dir,
            grid=grid,
            dof_um=dof_um,
            focus_map=focus_map,
            truth_um=truth_um,
            state=MappingProxyType(state),
            kept=MappingProxyType(dict(tally.kept)),
            planes=MappingProxyType({tile: tuple(z) for tile, z in tally.planes.items()}),
            measured=MappingProxyType(dict(tally.focus_measured)),
            phase=MappingProxyType(dict(tally.phase)),
            images_per_tile=images_per_tile,
            mosaic=mosaic,
            mosaic_format=mosaic_format,
            report=MappingProxyType(report),
            placement=placement,
        )

    @cached_property
    def shown_mosaic(self) -> tuple[np.ndarray, tuple[float, float] | None] | None:
        """The mosaic as the outputs show it, with its corner: the tiles side by side as the
        record holds them (`mosaic`; corner None), or, where they overlap, stitched at their
        `placement`, with the place (y, x px) of its corner relative to tile (0, 0)'s first
        pixel. None when no tile was kept."""
        if self.mosaic is None:
            return None
        if self.placement is None:
            return self.mosaic, None
        tiles = tiles_of_mosaic(self.mosaic, self.grid, self.kept)
        return compose(tiles, self.placement.places_px)

    @property
    def title(self) -> str:
        """What was scanned: "strategy on instrument/slide"."""
        state = self.state
        return f"{state.get('strategy')} on {state.get('instrument')}/{state.get('slide')}"

    @property
    def description(self) -> str:
        """The mosaic's description (OME-TIFF and OME-Zarr alike)."""
        return f"focustrack scan: {self.title}"

    def tile_metadata(self) -> list[dict[str, Any]]:
        """Every tile's numbers, row-major: where it is, its image, its last measurement, its map.

        Per tile: row, col, stage_x_um, stage_y_um; z_used_um (its kept image), planes_um (the
        frames it keeps besides, where one is too unsure: `ScanRecord.keep_planes`), best_z_um,
        sigma_um and flags (the last best focus posted for it; null and [] where none was),
        images (acquired on it), posterior_um, posterior_sigma_um and out_of_focus_risk (the
        estimator's map). Heights in um, null where there is none.
        """
        layers = map_layers(self.focus_map)
        grid = self.grid
        tiles = []
        for row in range(grid.rows):
            for col in range(grid.cols):
                measured = self.measured.get((row, col), {})
                x_um, y_um = grid.stage_xy_um(row, col)
                tiles.append(
                    {
                        "row": row,
                        "col": col,
                        "stage_x_um": x_um,
                        "stage_y_um": y_um,
                        "z_used_um": self.kept.get((row, col)),
                        "planes_um": list(self.planes.get((row, col), [])),
                        "best_z_um": measured.get("z_um"),
                        "sigma_um": measured.get("sigma_um"),
                        "flags": measured.get("flags", []),
                        "images": int(self.images_per_tile[row, col]),
                        "posterior_um": finite_or_none(layers["posterior_um"][row, col]),
                        "posterior_sigma_um": finite_or_none(
                            layers["posterior_sigma_um"][row, col]
                        ),
                        "out_of_focus_risk": finite_or_none(layers["out_of_focus_risk"][row, col]),
                    }
                )
        return tiles


class OutputWriter(Protocol):
    """One output of a finished scan, written into `scan.out_dir`."""

    def write(self, scan: FinishedScan) -> list[Path]:
        """Write the output's files (none where the scan has nothing for it); their paths."""
        ...


def write_outputs(scan: FinishedScan, writers: Sequence[OutputWriter]) -> list[Path]:
    """Run each writer on `scan`, in order; every path written.

    Once they all have, and the mosaic file is among what they wrote, the record's
    partial mosaic goes: a writer that fails leaves it, so that running the scan again
    on its folder writes every output again from it. What only the tiles could tell, the
    stitched mosaic's seam error, is kept in the scan's state first, for the report of
    the finished scan run again.
    """
    paths = [path for writer in writers for path in writer.write(scan)]
    if scan.out_dir / scan.mosaic_format.file_name in paths:
        if (seam_error_px := scan.report.get("seam_error_px")) is not None:
            ScanState(scan.out_dir / STATE_FILE).save(**{SEAM_STATE_KEY: seam_error_px})
        (scan.out_dir / PARTIAL_MOSAIC).unlink(missing_ok=True)
    return paths
