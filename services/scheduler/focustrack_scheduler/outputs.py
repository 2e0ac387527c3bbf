"""What a scan leaves in its output folder, and the durable record it resumes from.

During the scan (`ScanRecord`):
- ``scan.json``: which scan this folder holds (estimator URL and slide id, instrument,
  slide, strategy; the tile format once known), written when the slide is created;
- ``scan_log.jsonl``: one line per acquisition made (tile, frames, simulated seconds),
  per measurement posted (tile, best z, sigma, flags), per tile image kept (tile, z) and
  per tile that keeps several frames (tile, their z), appended and flushed as they happen;
- ``mosaic.partial.npy``: the mosaic being filled in, a memory map on disk;
- ``planes/r{row}_c{col}.npy``: the frames a tile keeps where one is too unsure to be in
  focus (`Outcome.planes_um`), (n, h, w, channels) as the camera gave them, ascending in z;
  the tile's image in the mosaic is then their fusion (`fusion.fuse_planes`).
A scheduler that is restarted on the same folder reads these back and carries on.

At the end (`write_outputs`):
- ``focus_map.csv`` / ``focus_map.npy``: every layer of the estimator's map (prior,
  posterior and smoothed heights with their sigma, z used), as the estimator exports them;
- ``report.json``: images acquired, simulated scan time, in-focus fraction and MAE against
  the instrument's truth, and the wall-time split;
- ``scan.png``: true surface, estimated map, error map, images per tile;
- the in-focus tile images side by side (8-bit RGB, with a pyramid) for a slide viewer:
  ``mosaic.ome.zarr`` (OME-Zarr, NGFF 0.5: the default; each tile's best z, sigma and flags
  in its attributes, the focus-map layers as arrays beside it) or ``mosaic.ome.tif``
  (`MosaicFormat`), and ``mosaic.png``, a small preview.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import zarr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure

from focustrack_core.domain import (
    Acquisition,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    kept_in_focus,
)
from focustrack_core.fusion import fuse_planes
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import MAP_LAYERS, finite_or_none, map_csv, map_layers, map_npy

STATE_FILE = "scan.json"
LOG_FILE = "scan_log.jsonl"
PARTIAL_MOSAIC = "mosaic.partial.npy"
MOSAIC = "mosaic.ome.tif"
MOSAIC_ZARR = "mosaic.ome.zarr"
MOSAIC_PREVIEW = "mosaic.png"
REPORT = "report.json"
PLOTS = "scan.png"
FOCUS_MAP_CSV = "focus_map.csv"
FOCUS_MAP_NPY = "focus_map.npy"
PLANES = "planes"
#: Every file a scan writes in its output folder.
SCAN_FILES = (
    STATE_FILE,
    LOG_FILE,
    PARTIAL_MOSAIC,
    MOSAIC,
    MOSAIC_ZARR,
    MOSAIC_PREVIEW,
    REPORT,
    PLOTS,
    FOCUS_MAP_CSV,
    FOCUS_MAP_NPY,
    PLANES,
)

#: Side of the TIFF tiles, and the smallest pyramid level written, in pixels.
TIFF_TILE_PX = 256
#: Longest side of the PNG preview of the mosaic, in pixels.
PREVIEW_PX = 1600
#: Group of the OME-Zarr mosaic that holds the focus-map layers, one NGFF image each.
ZARR_MAPS = "maps"
#: Key of FocusTrack's own attributes in the OME-Zarr root (`tile_metadata`).
ZARR_ATTRS = "focustrack"


class MosaicFormat(StrEnum):
    """The file the mosaic of a scan is written as."""

    OME_ZARR = "ome-zarr"  # mosaic.ome.zarr: NGFF 0.5, lazy in napari and the OME viewers
    OME_TIFF = "ome-tiff"  # mosaic.ome.tif: a tiled pyramid for QuPath and slide viewers

    @property
    def file_name(self) -> str:
        return MOSAIC_ZARR if self is MosaicFormat.OME_ZARR else MOSAIC


@dataclass
class WallTimes:
    """Where the scan's wall-clock seconds went, as the scheduler saw them (they add up to total).

    - rendering: acquire request sent -> stack published (the instrument rendering it);
    - transport: stack published -> acquire reply and stack both received;
    - focus_computation: the focus service's own compute time of the stacks awaited;
    - estimation: the estimator's HTTP calls (next, measurements, slide creation);
    - waiting: the rest of the wait for focus results (their queueing and travel);
    - scheduler: everything else (tile images, the log, the progress display).
    """

    rendering_s: float = 0.0
    transport_s: float = 0.0
    focus_computation_s: float = 0.0
    estimation_s: float = 0.0
    waiting_s: float = 0.0
    scheduler_s: float = 0.0
    total_s: float = 0.0

    def close(self, total_s: float) -> None:
        """Set the total; what no other part accounts for is the scheduler's own."""
        self.total_s = total_s
        parts = (self.rendering_s, self.transport_s, self.focus_computation_s)
        self.scheduler_s = max(0.0, total_s - sum(parts) - self.estimation_s - self.waiting_s)

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def to_uint8(frame: np.ndarray, bit_depth: int) -> np.ndarray:
    """A camera frame (h, w, channels) of `bit_depth` bits as 8 bits per channel."""
    scale = 255.0 / (2**bit_depth - 1)
    return np.clip(np.rint(frame * scale), 0, 255).astype(np.uint8)


class ScanRecord:
    """The durable record of one scan in `out_dir` (see the module docstring)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.acquisitions: list[dict[str, Any]] = []
        self.kept: dict[tuple[int, int], float] = {}  # tile -> z (um) of its image
        self.planes: dict[tuple[int, int], list[float]] = {}  # tile -> z (um) of its frames
        self.measured: dict[tuple[int, int], dict[str, Any]] = {}  # tile -> its last measurement
        log_path = self.out_dir / LOG_FILE
        if log_path.exists():
            for line in log_path.read_text().splitlines():
                try:
                    self._take(json.loads(line))
                except (ValueError, KeyError):  # a line cut short by a kill: the rest is intact
                    continue
        self._log = log_path.open("a")
        #: Called with every entry appended from now on (the live view follows the scan).
        self.listeners: list[Callable[[dict[str, Any]], None]] = []
        self._mosaic: np.memmap | None = None

    @property
    def state(self) -> dict[str, Any] | None:
        path = self.out_dir / STATE_FILE
        return json.loads(path.read_text()) if path.exists() else None

    def save_state(self, **entries: Any) -> None:
        """Merge `entries` into scan.json (written whole, then renamed: never half a file)."""
        state = {**(self.state or {}), **entries}
        temporary = self.out_dir / (STATE_FILE + ".tmp")
        temporary.write_text(json.dumps(state, indent=2) + "\n")
        temporary.replace(self.out_dir / STATE_FILE)

    def _take(self, entry: dict[str, Any]) -> None:
        if entry["event"] == "acquired":
            self.acquisitions.append(entry)
        elif entry["event"] == "kept":
            self.kept[(entry["row"], entry["col"])] = entry["z_um"]
        elif entry["event"] == "planes":
            self.planes[(entry["row"], entry["col"])] = entry["z_um"]
        elif entry["event"] == "measured":
            self.measured[(entry["row"], entry["col"])] = entry

    def _append(self, entry: dict[str, Any]) -> None:
        self._log.write(json.dumps(entry) + "\n")
        self._log.flush()
        self._take(entry)
        for listener in self.listeners:
            listener(entry)

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
                "z_um": measurement.z_um,
                "sigma_um": measurement.sigma_um,
                "flags": sorted(str(flag) for flag in measurement.flags),
                "posterior_um": finite_or_none(outcome.posterior_um),
                "posterior_sigma_um": finite_or_none(outcome.posterior_sigma_um),
                "curve_z_um": None if curve is None else curve[0],
                "curve_scores": None if curve is None else curve[1],
            }
        )

    def keep(
        self, grid: ScanGrid, row: int, col: int, z_um: float, image: np.ndarray, bit_depth: int
    ) -> None:
        """Tile (row, col)'s image (h, w, channels) at `z_um` goes into the mosaic."""
        self._write_tile(grid, row, col, image, bit_depth)
        self._append({"event": "kept", "row": row, "col": col, "z_um": z_um})

    def _write_tile(
        self, grid: ScanGrid, row: int, col: int, image: np.ndarray, bit_depth: int
    ) -> None:
        mosaic = self._open_mosaic(grid, image.shape)
        height, width = image.shape[:2]
        mosaic[row * height : (row + 1) * height, col * width : (col + 1) * width] = to_uint8(
            image, bit_depth
        )

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
        folder = self.out_dir / PLANES
        folder.mkdir(exist_ok=True)
        path = folder / f"r{row}_c{col}.npy"
        temporary = path.with_suffix(".tmp")
        with temporary.open("wb") as file:  # written whole, then renamed: never half a file
            np.save(file, frames, allow_pickle=False)
        temporary.replace(path)
        self._write_tile(grid, row, col, fuse_planes(frames), bit_depth)
        self._append(
            {
                "event": "planes",
                "row": row,
                "col": col,
                "z_um": z_um,
                "file": f"{PLANES}/{path.name}",
            }
        )

    def tiles_in_focus(self, truth_um: np.ndarray, dof_um: float) -> int:
        """Tiles with a kept frame (its image, or one of its planes) within dof/2 of their
        true focus `truth_um` (rows, cols), in um."""
        if not self.kept:
            return 0
        # Vectorised over the images (the progress bar asks after every tile: a loop in
        # Python over 40 000 tiles each time would be quadratic); the few tiles that keep
        # planes are then judged on all of them (their planes hold their image too).
        rows, cols = np.array(list(self.kept)).T
        z_um = np.array(list(self.kept.values()))
        n_in_focus = int(np.count_nonzero(np.abs(z_um - truth_um[rows, cols]) <= dof_um / 2.0))
        for tile, planes_um in self.planes.items():
            if tile in self.kept:
                image_in_focus = kept_in_focus([self.kept[tile]], truth_um[tile], dof_um)
                n_in_focus += kept_in_focus(planes_um, truth_um[tile], dof_um) - image_in_focus
        return n_in_focus

    @property
    def frames_kept(self) -> int:
        """Frames kept over all tiles (one per tile, all of its planes where it keeps some)."""
        return len(self.kept) + sum(len(z_um) - 1 for z_um in self.planes.values())

    def _open_mosaic(self, grid: ScanGrid, tile_shape: tuple[int, ...]) -> np.memmap:
        if self._mosaic is None:
            height, width, channels = tile_shape
            shape = (grid.rows * height, grid.cols * width, channels)
            path = self.out_dir / PARTIAL_MOSAIC
            if path.exists():
                self._mosaic = np.lib.format.open_memmap(path, mode="r+")
                if self._mosaic.shape != shape:
                    raise ValueError(
                        f"{path} holds a {self._mosaic.shape} mosaic; tiles of {tile_shape} on "
                        f"a {grid.rows}x{grid.cols} grid need {shape}: use a new output folder"
                    )
            else:
                self._mosaic = np.lib.format.open_memmap(
                    path, mode="w+", dtype=np.uint8, shape=shape
                )
        return self._mosaic

    @property
    def n_images(self) -> int:
        return sum(entry["n_frames"] for entry in self.acquisitions)

    @property
    def scan_time_s(self) -> float:
        return float(sum(entry["scan_time_s"] for entry in self.acquisitions))

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

    def close(self) -> None:
        self._log.close()
        if self._mosaic is not None:
            self._mosaic.flush()
            self._mosaic = None


def mean_abs_error_um(estimate_um: np.ndarray, truth_um: np.ndarray) -> float | None:
    """Mean |estimate - truth| over the tiles that have an estimate (None if none has)."""
    error = np.abs(estimate_um - truth_um)
    return float(np.nanmean(error)) if np.isfinite(error).any() else None


def predicted_in_focus_fraction(focus_map: FocusMap) -> float | None:
    """The share of imaged tiles the estimator expects in focus: 1 - their mean predicted
    out-of-focus risk (None where it states none)."""
    risk = focus_map.out_of_focus_risk
    if risk is None or not np.isfinite(risk).any():
        return None
    return 1.0 - float(np.nanmean(risk))


def tile_metadata(record: ScanRecord, grid: ScanGrid, focus_map: FocusMap) -> list[dict[str, Any]]:
    """Every tile's numbers, row-major: where it is, its image, its last measurement, its map.

    Per tile: row, col, stage_x_um, stage_y_um; z_used_um (its kept image), planes_um (the
    frames it keeps besides, where one is too unsure: `ScanRecord.keep_planes`), best_z_um,
    sigma_um and flags (the last best focus posted for it; null and [] where none was),
    images (acquired on it), posterior_um, posterior_sigma_um and out_of_focus_risk (the
    estimator's map). Heights in um, null where there is none.
    """
    layers = map_layers(focus_map)
    images = record.images_per_tile(grid)
    tiles = []
    for row in range(grid.rows):
        for col in range(grid.cols):
            measured = record.measured.get((row, col), {})
            x_um, y_um = grid.stage_xy_um(row, col)
            tiles.append(
                {
                    "row": row,
                    "col": col,
                    "stage_x_um": x_um,
                    "stage_y_um": y_um,
                    "z_used_um": record.kept.get((row, col)),
                    "planes_um": record.planes.get((row, col), []),
                    "best_z_um": measured.get("z_um"),
                    "sigma_um": measured.get("sigma_um"),
                    "flags": measured.get("flags", []),
                    "images": int(images[row, col]),
                    "posterior_um": finite_or_none(layers["posterior_um"][row, col]),
                    "posterior_sigma_um": finite_or_none(layers["posterior_sigma_um"][row, col]),
                    "out_of_focus_risk": finite_or_none(layers["out_of_focus_risk"][row, col]),
                }
            )
    return tiles


def write_mosaic(
    record: ScanRecord,
    grid: ScanGrid,
    focus_map: FocusMap,
    mosaic_format: MosaicFormat,
    description: str,
) -> tuple[Path, Path] | None:
    """Turn the partial mosaic into `mosaic_format` and a PNG preview (None if there is none)."""
    out_dir = record.out_dir
    partial = out_dir / PARTIAL_MOSAIC
    tile = (record.state or {}).get("tile")
    if tile is None or not partial.exists():
        return None
    mosaic = np.load(partial, mmap_mode="r")
    pixel_size_um = float(tile["pixel_size_um"])
    n_levels = max(0, math.floor(math.log2(min(mosaic.shape[:2]) / TIFF_TILE_PX)))
    path = out_dir / mosaic_format.file_name
    if mosaic_format is MosaicFormat.OME_TIFF:
        _write_ome_tiff(path, mosaic, pixel_size_um, n_levels, description)
    else:
        attributes = {
            "description": description,
            "scan": {name: value for name, value in (record.state or {}).items() if name != "tile"},
            "grid": {"rows": grid.rows, "cols": grid.cols, "pitch_um": grid.pitch_um},
            "tile_px": {"height": tile["height"], "width": tile["width"]},
            "pixel_size_um": pixel_size_um,
            "maps": {name: f"{ZARR_MAPS}/{name}" for name in (*MAP_LAYERS, "images")},
            "tiles": tile_metadata(record, grid, focus_map),
        }
        layers = {**map_layers(focus_map), "images": record.images_per_tile(grid)}
        _write_ome_zarr(path, mosaic, pixel_size_um, n_levels, attributes, layers)
    step = max(1, math.ceil(max(mosaic.shape[:2]) / PREVIEW_PX))
    preview = out_dir / MOSAIC_PREVIEW
    _save_image(preview, np.asarray(mosaic[::step, ::step]))
    partial.unlink()
    return path, preview


def _write_ome_tiff(
    path: Path, mosaic: np.ndarray, pixel_size_um: float, n_levels: int, description: str
) -> None:
    """The mosaic (height, width, channels) uint8 as a tiled OME-TIFF with `n_levels` halvings."""
    options: dict[str, Any] = {
        "photometric": "rgb" if mosaic.shape[-1] == 3 else "minisblack",
        "tile": (TIFF_TILE_PX, TIFF_TILE_PX),
        "resolutionunit": "CENTIMETER",
    }
    metadata = {
        "axes": "YXS",
        "PhysicalSizeX": pixel_size_um,
        "PhysicalSizeXUnit": "µm",
        "PhysicalSizeY": pixel_size_um,
        "PhysicalSizeYUnit": "µm",
        "Description": description,
    }
    per_cm = 1e4 / pixel_size_um
    with tifffile.TiffWriter(path, bigtiff=mosaic.nbytes > 2**31) as tif:
        tif.write(
            mosaic,
            subifds=n_levels,
            resolution=(per_cm, per_cm),
            metadata=metadata,
            **options,
        )
        level = np.asarray(mosaic)
        for index in range(1, n_levels + 1):
            level = _half(level)  # a 2x2 mean: a viewer's zoomed-out level without aliasing
            scale = per_cm / 2**index
            tif.write(level, subfiletype=1, resolution=(scale, scale), **options)


#: Colours of the mosaic's channels in OME-Zarr's "omero" rendering settings.
_CHANNEL_COLOURS = (("red", "FF0000"), ("green", "00FF00"), ("blue", "0000FF"))
_SPACE = {"type": "space", "unit": "micrometer"}
#: NGFF version written (https://ngff.openmicroscopy.org/0.5/).
NGFF_VERSION = "0.5"


def _write_ome_zarr(
    path: Path,
    mosaic: np.ndarray,
    pixel_size_um: float,
    n_levels: int,
    attributes: dict[str, Any],
    layers: dict[str, np.ndarray],
) -> None:
    """The mosaic (height, width, channels) uint8 as an NGFF image (c, y, x) with `n_levels`
    2x2-mean halvings, `attributes` under `ZARR_ATTRS`, and each (rows, cols) layer as an NGFF
    image in `ZARR_MAPS`, one pixel per tile, placed over its tile of the mosaic (micrometres).
    """
    root = zarr.open_group(path, mode="w", zarr_format=3)
    levels = [mosaic]
    for _ in range(n_levels):
        levels.append(_half(np.asarray(levels[-1])))  # as the OME-TIFF's pyramid
    channels = [
        {"label": label, "color": colour, "window": {"start": 0, "end": 255, "min": 0, "max": 255}}
        for label, colour in _CHANNEL_COLOURS[: mosaic.shape[-1]]
    ]
    _write_ngff_image(
        root,
        "mosaic",
        [level.transpose(2, 0, 1) for level in levels],
        pixel_um=(pixel_size_um, pixel_size_um),
        origin_um=(0.0, 0.0),
        omero={"channels": channels, "rdefs": {"model": "color"}},
    )
    root.attrs[ZARR_ATTRS] = attributes
    rows, cols = next(iter(layers.values())).shape
    tile_um = (mosaic.shape[0] / rows * pixel_size_um, mosaic.shape[1] / cols * pixel_size_um)
    # A tile's value sits at the centre of its tile of the mosaic (NGFF places pixel centres).
    centre_um = ((tile_um[0] - pixel_size_um) / 2, (tile_um[1] - pixel_size_um) / 2)
    maps = root.create_group(ZARR_MAPS)
    for name, values in layers.items():
        group = maps.create_group(name)
        _write_ngff_image(group, name, [np.asarray(values)], tile_um, centre_um)
        unit = {"images": "images", "out_of_focus_risk": "probability"}.get(name, "um")
        group.attrs[ZARR_ATTRS] = {"layer": name, "unit": unit}


def _write_ngff_image(
    group: zarr.Group,
    name: str,
    levels: list[np.ndarray],
    pixel_um: tuple[float, float],
    origin_um: tuple[float, float],
    **metadata: Any,
) -> None:
    """An NGFF multiscale image in `group`: `levels` (c, y, x) or (y, x), each half the last.

    `pixel_um` is level 0's pixel size (y, x) and `origin_um` the centre of its first pixel.
    """
    names = ["c", "y", "x"][-levels[0].ndim :]
    axes = [{"name": "c", "type": "channel"}] if levels[0].ndim == 3 else []
    axes += [{"name": axis, **_SPACE} for axis in ("y", "x")]
    datasets: list[dict[str, Any]] = []
    for index, level in enumerate(levels):
        factor = 2**index
        chunks = (*level.shape[:-2], *(min(side, 2 * TIFF_TILE_PX) for side in level.shape[-2:]))
        array = group.create_array(
            f"s{index}", shape=level.shape, dtype=level.dtype, chunks=chunks, dimension_names=names
        )
        array[...] = level
        scale = [size * factor for size in pixel_um]
        # the centre of a level's first pixel: the mean of the factor x factor it averages
        translation = [
            o + (factor - 1) * size / 2 for o, size in zip(origin_um, pixel_um, strict=True)
        ]
        channel = [1.0] if level.ndim == 3 else []
        channel_offset = [0.0] if level.ndim == 3 else []
        datasets.append(
            {
                "path": f"s{index}",
                "coordinateTransformations": [
                    {"type": "scale", "scale": channel + scale},
                    {"type": "translation", "translation": channel_offset + translation},
                ],
            }
        )
    multiscale: dict[str, Any] = {"name": name, "axes": axes, "datasets": datasets}
    group.attrs["ome"] = {"version": NGFF_VERSION, "multiscales": [multiscale], **metadata}


def _half(image: np.ndarray) -> np.ndarray:
    height, width = (image.shape[0] // 2) * 2, (image.shape[1] // 2) * 2
    blocks = image[:height, :width].reshape(height // 2, 2, width // 2, 2, -1)
    return blocks.mean(axis=(1, 3)).round().astype(image.dtype)


def _save_image(path: Path, image: np.ndarray) -> None:
    figure = Figure(figsize=(image.shape[1] / 100, image.shape[0] / 100), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_axes((0, 0, 1, 1))
    axes.imshow(image.squeeze(), cmap="gray", interpolation="nearest")
    axes.set_axis_off()
    figure.savefig(path, dpi=100)


def write_plots(
    path: Path,
    focus_map: FocusMap,
    truth_um: np.ndarray | None,
    images_per_tile: np.ndarray,
    title: str,
) -> Path:
    """True surface, estimated (posterior) map, error map and images per tile, as one PNG."""
    figure = Figure(figsize=(11, 9), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(2, 2).ravel()
    posterior_um = np.ma.masked_invalid(focus_map.posterior_um)
    heights = [posterior_um] + ([truth_um] if truth_um is not None else [])
    low_um = float(min(np.ma.min(h) for h in heights))
    high_um = float(max(np.ma.max(h) for h in heights))
    panels: list[tuple[Any, str, str, str, dict[str, Any]]] = [
        (posterior_um, "estimated focus map (posterior)", "um", "viridis", {}),
        (images_per_tile, "images per tile", "images", "cividis", {}),
    ]
    if truth_um is not None:
        error_um = np.ma.masked_invalid(focus_map.posterior_um - truth_um)
        limit_um = max(float(np.ma.max(np.abs(error_um))), 1e-3)
        norm = TwoSlopeNorm(0.0, -limit_um, limit_um)
        panels.insert(0, (truth_um, "true focus surface", "um", "viridis", {}))
        panels.insert(2, (error_um, "error: posterior - truth", "um", "RdBu_r", {"norm": norm}))
    for ax, (values, name, unit, cmap, extra) in zip(axes, panels, strict=False):
        if unit == "um" and "norm" not in extra:
            extra = {"vmin": low_um, "vmax": high_um}
        image = ax.imshow(values, cmap=cmap, origin="upper", **extra)
        ax.set(title=name, xlabel="col (x)", ylabel="row (y)")
        figure.colorbar(image, ax=ax, label=unit)
    for ax in axes[len(panels) :]:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no truth from the instrument", ha="center", va="center")
    figure.suptitle(title)
    figure.savefig(path, dpi=90)
    return path


def write_outputs(
    record: ScanRecord,
    grid: ScanGrid,
    focus_map: FocusMap,
    truth_um: np.ndarray | None,
    dof_um: float,
    wall: WallTimes,
    mosaic_format: MosaicFormat = MosaicFormat.OME_ZARR,
    focus_results_rejected: int = 0,
) -> dict[str, Any]:
    """Write the focus map, plots, mosaic and report of a finished scan; return the report.

    `focus_results_rejected`: results dropped for want of a trusted tag (this run's)."""
    out_dir = record.out_dir
    state = record.state or {}
    (out_dir / FOCUS_MAP_CSV).write_text(map_csv(focus_map, grid))
    (out_dir / FOCUS_MAP_NPY).write_bytes(map_npy(focus_map))
    z_kept_um = record.z_kept_um(grid)
    images = record.images_per_tile(grid)
    title = f"{state.get('strategy')} on {state.get('instrument')}/{state.get('slide')}"
    write_plots(out_dir / PLOTS, focus_map, truth_um, images, title)
    write_mosaic(record, grid, focus_map, mosaic_format, f"focustrack scan: {title}")
    report = {
        "instrument": state.get("instrument"),
        "slide": state.get("slide"),
        "strategy": state.get("strategy"),
        "estimator": state.get("estimator"),
        "estimator_slide_id": state.get("slide_id"),
        "rows": grid.rows,
        "cols": grid.cols,
        "tiles_imaged": int(np.isfinite(z_kept_um).sum()),
        "acquisitions": len(record.acquisitions),
        "retries": sum(entry["purpose"] == Purpose.RETRY for entry in record.acquisitions),
        "images_acquired": record.n_images,
        "images_per_tile": record.n_images / grid.n_tiles,
        "frames_kept_per_tile": record.frames_kept / grid.n_tiles,
        "scan_time_s": record.scan_time_s,
        "dof_um": dof_um,
        "in_focus_fraction": None
        if truth_um is None
        else record.tiles_in_focus(truth_um, dof_um) / grid.n_tiles,
        "predicted_in_focus_fraction": predicted_in_focus_fraction(focus_map),
        "mae_um": None if truth_um is None else mean_abs_error_um(focus_map.posterior_um, truth_um),
        "prior_mae_um": None
        if truth_um is None
        else mean_abs_error_um(focus_map.prior_um, truth_um),
        "wall_time_s": wall.as_dict(),
        "focus_results_rejected": focus_results_rejected,
        "mosaic": mosaic_format.file_name if (out_dir / mosaic_format.file_name).exists() else None,
    }
    (out_dir / REPORT).write_text(json.dumps(report, indent=2) + "\n")
    return report
