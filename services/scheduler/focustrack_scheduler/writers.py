"""The outputs of a finished scan, one writer each (`finished.OutputWriter`).

`DEFAULT_WRITERS` is what every scan writes (`outputs` lists the files). A writer imports
its file format's library when it writes (matplotlib, Pillow, zarr, tifffile), so a scan, or its
``--help``, does not load them before its end. The order matters once:
`OmeZarrMetadataWriter` adds to the OME-Zarr group that `MosaicWriter` made. The
record's partial mosaic goes when every writer is done (`finished.write_outputs`).
`PhaseWriter` adds the phase to the same group, where tiles have one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from focustrack_core.maps import MAP_LAYERS, map_csv, map_layers, map_npy
from focustrack_scheduler.finished import FinishedScan, OutputWriter
from focustrack_scheduler.outputs import (
    FOCUS_MAP_CSV,
    FOCUS_MAP_NPY,
    MOSAIC_PREVIEW,
    PLANES,
    PLOTS,
    REPORT,
    ZARR_MAPS,
    MosaicFormat,
)
from focustrack_scheduler.stitch import compose

#: Longest side of the PNG preview of the mosaic, in pixels.
PREVIEW_PX = 1600


class FocusMapWriter:
    """``focus_map.csv`` and ``focus_map.npy``: every layer of the estimator's map."""

    def write(self, scan: FinishedScan) -> list[Path]:
        csv, npy = scan.out_dir / FOCUS_MAP_CSV, scan.out_dir / FOCUS_MAP_NPY
        csv.write_text(map_csv(scan.focus_map, scan.grid))
        npy.write_bytes(map_npy(scan.focus_map))
        return [csv, npy]


class PlotsWriter:
    """``scan.png``: true surface, estimated map, error map, images per tile."""

    def write(self, scan: FinishedScan) -> list[Path]:
        from focustrack_scheduler.plots import write_plots

        path = scan.out_dir / PLOTS
        return [write_plots(path, scan.focus_map, scan.truth_um, scan.images_per_tile, scan.title)]


class MosaicPreviewWriter:
    """``mosaic.png``: the mosaic at most `PREVIEW_PX` on its longest side (where there is one)."""

    def write(self, scan: FinishedScan) -> list[Path]:
        if scan.shown_mosaic is None:
            return []
        from PIL import Image

        mosaic, _ = scan.shown_mosaic
        step = max(1, math.ceil(max(mosaic.shape[:2]) / PREVIEW_PX))
        preview = mosaic[::step, ::step]
        if preview.shape[2] == 1:  # one channel: a grey PNG
            preview = preview[..., 0]
        path = scan.out_dir / MOSAIC_PREVIEW
        # Pillow straight, pixel for pixel: a matplotlib figure of the same pixels took
        # four times as long (1.5 s for a 1536 px mosaic) and wrote RGBA.
        Image.fromarray(np.ascontiguousarray(preview)).save(path)
        return [path]


class MosaicWriter:
    """The mosaic in the scan's format (``mosaic.ome.zarr`` or ``mosaic.ome.tif``), which then
    replaces the partial mosaic of the record (`finished.write_outputs` removes it)."""

    def write(self, scan: FinishedScan) -> list[Path]:
        if scan.shown_mosaic is None:
            return []
        mosaic, corner_px = scan.shown_mosaic
        path = scan.out_dir / scan.mosaic_format.file_name
        pixel_size_um = float(scan.state["tile"]["pixel_size_um"])
        if scan.mosaic_format is MosaicFormat.OME_TIFF:
            from focustrack_scheduler.ome_tiff import write_ome_tiff

            write_ome_tiff(path, mosaic, pixel_size_um, scan.description)
        else:
            from focustrack_scheduler.ome_zarr import write_mosaic

            write_mosaic(path, mosaic, pixel_size_um, origin_um(scan, corner_px))
        return [path]


class OmeZarrMetadataWriter:
    """Into ``mosaic.ome.zarr``: the scan, the grid and every tile's numbers as attributes,
    and the focus-map layers (and images per tile) as NGFF images beside the mosaic."""

    def write(self, scan: FinishedScan) -> list[Path]:
        if scan.mosaic is None or scan.mosaic_format is not MosaicFormat.OME_ZARR:
            return []
        from focustrack_scheduler.ome_zarr import write_metadata

        tile = scan.state["tile"]
        grid = scan.grid
        pixel_size_um = float(tile["pixel_size_um"])
        attributes = {
            "description": scan.description,
            "scan": {name: value for name, value in scan.state.items() if name != "tile"},
            "grid": {"rows": grid.rows, "cols": grid.cols, "pitch_um": grid.pitch_um},
            "tile_px": {"height": tile["height"], "width": tile["width"]},
            "pixel_size_um": pixel_size_um,
            "maps": {name: f"{ZARR_MAPS}/{name}" for name in (*MAP_LAYERS, "images")},
            "tiles": scan.tile_metadata(),
        }
        layers = {**map_layers(scan.focus_map), "images": scan.images_per_tile}
        path = scan.out_dir / scan.mosaic_format.file_name
        stage = None
        if scan.placement is not None:  # a value per tile at the tile's stage position
            x_um, y_um = grid.stage_xy_um(0, 0)
            stage = (grid.pitch_um, (y_um, x_um))
        write_metadata(path, scan.mosaic.shape, pixel_size_um, attributes, layers, stage)
        return [path]


def origin_um(scan: FinishedScan, corner_px: tuple[float, float] | None) -> tuple[float, float]:
    """Where (y, x, um) a layer whose corner is `corner_px` (`FinishedScan.shown_mosaic`)
    puts its first pixel's centre: at the stage's coordinates where the tiles were stitched,
    at (0, 0) where they lie side by side (corner None)."""
    return (0.0, 0.0) if corner_px is None else stage_origin_um(scan, corner_px)


def stage_origin_um(scan: FinishedScan, corner_px: tuple[float, float]) -> tuple[float, float]:
    """Stage coordinates (y, x), um, of the centre of the pixel `corner_px` (y, x) from tile
    (0, 0)'s first pixel, where the stage placed that tile."""
    tile = scan.state["tile"]
    pixel_um = float(tile["pixel_size_um"])
    x_um, y_um = scan.grid.stage_xy_um(0, 0)
    return (
        y_um - (int(tile["height"]) / 2 - 0.5 - corner_px[0]) * pixel_um,
        x_um - (int(tile["width"]) / 2 - 0.5 - corner_px[1]) * pixel_um,
    )


class PlanesWriter:
    """Into ``mosaic.ome.zarr``: the frames each uncertain tile keeps (``planes/`` of the
    record), an NGFF image (c, z, y, x) each where the tile lies, their z in its attributes."""

    def write(self, scan: FinishedScan) -> list[Path]:
        if not scan.planes or scan.mosaic is None:
            return []
        if scan.mosaic_format is not MosaicFormat.OME_ZARR:
            return []  # the planes stay in planes/
        from focustrack_scheduler.ome_zarr import write_planes

        tile = scan.state["tile"]
        height, width = int(tile["height"]), int(tile["width"])
        pixel_um = float(tile["pixel_size_um"])
        path = scan.out_dir / scan.mosaic_format.file_name
        for (row, col), z_um in scan.planes.items():
            file = scan.out_dir / PLANES / f"r{row}_c{col}.npy"
            if not file.exists():  # its frames were gone when the scan kept them (logged)
                continue
            if scan.placement is None:  # where its image lies in the mosaic, side by side
                origin_um = (row * height * pixel_um, col * width * pixel_um)
            else:
                origin_um = stage_origin_um(scan, scan.placement.places_px[(row, col)])
            frames = np.load(file)
            write_planes(path, (row, col), frames, list(z_um), pixel_um, origin_um)
        return [path]


def phase_mosaic(scan: FinishedScan) -> tuple[np.ndarray, tuple[float, float] | None]:
    """The tiles' phase (rad) where the mosaic shows their images, float32 (height, width)
    pixel for pixel over it, NaN where a tile has none; with the mosaic's corner
    (`FinishedScan.shown_mosaic`): side by side, or stitched where the tiles overlap."""
    tiles = {  # mapped, not read: each tile is read once, into the canvas
        tile: np.load(scan.out_dir / file, mmap_mode="r")[0] for tile, file in scan.phase.items()
    }
    if scan.placement is not None:
        places_px = scan.placement.places_px
        placed = {tile: phase for tile, phase in tiles.items() if tile in places_px}
        return compose(placed, places_px, canvas_tiles=scan.kept, fill=np.nan)
    tile = scan.state["tile"]
    height, width = int(tile["height"]), int(tile["width"])
    mosaic = np.full((scan.grid.rows * height, scan.grid.cols * width), np.nan, np.float32)
    for (row, col), phase_rad in tiles.items():
        mosaic[row * height : (row + 1) * height, col * width : (col + 1) * width] = phase_rad
    return mosaic, None


class PhaseWriter:
    """Into ``mosaic.ome.zarr``: the tiles' phase in radians (``--phase``), an NGFF image
    ``phase`` beside the mosaic, each tile where its image is (`phase_mosaic`)."""

    def write(self, scan: FinishedScan) -> list[Path]:
        if not scan.phase or scan.mosaic is None:
            return []
        if scan.mosaic_format is not MosaicFormat.OME_ZARR:
            return []  # the phase is a layer of the OME-Zarr; its tiles stay in phase/
        from focustrack_scheduler.ome_zarr import write_phase

        path = scan.out_dir / scan.mosaic_format.file_name
        phase_rad, corner_px = phase_mosaic(scan)
        pixel_size_um = float(scan.state["tile"]["pixel_size_um"])
        write_phase(path, phase_rad, pixel_size_um, origin_um(scan, corner_px))
        return [path]


class ReportWriter:
    """``report.json``: the scan's figures (`FinishedScan.report`)."""

    def write(self, scan: FinishedScan) -> list[Path]:
        path = scan.out_dir / REPORT
        path.write_text(json.dumps(dict(scan.report), indent=2) + "\n")
        return [path]


#: What every scan writes, in this order (see the module docstring).
DEFAULT_WRITERS: tuple[OutputWriter, ...] = (
    FocusMapWriter(),
    PlotsWriter(),
    MosaicPreviewWriter(),
    MosaicWriter(),
    OmeZarrMetadataWriter(),
    PlanesWriter(),
    PhaseWriter(),
    ReportWriter(),
)
