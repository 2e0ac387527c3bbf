"""A second pass placed where the first pass's tiles were: its lateral offset, measured and
applied to the stage.

Between passes the slide moves on the stage by a few um (repeatability, thermal
expansion). With ``focustrack scan --first-pass DIR`` the scheduler compares the images
of the pass's first tiles with the first pass's images of the same places (its mosaic,
``DIR/mosaic.ome.zarr``) by bounded phase correlation (`lateral.phase_shift`, each tile
as it is kept); once `Realign.tiles` of them are confident, their median
(`lateral.combined`) is the offset, and every later acquisition asks the instrument
to move the stage by it (the AcquireRequest's ``stage_offset_x_um``/``_y_um``), and the
tiles imaged before are taken again there, one frame at their image's z (`Retake`).
A tile imaged with one frame at its prediction is compared with the first pass's image of
it (`LateralPlacement.sharpness_ratio`, `focus_check`): a frame found out of focus is
measured.

Sign: a feature that lay at image pixel p in the first pass lies at p + s in the second
(s = (dy, dx) px, `lateral.Shift`): the slide moved by s on the stage, so the stage goes
s further (x along the image's columns, y along its rows) to show it where it was.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.focus_check import MIN_SHARPNESS_RATIO, sharpness_ratio
from focustrack_scheduler.lateral import MIN_SHARPNESS, Shift, combined, grey, phase_shift
from focustrack_scheduler.outputs import MOSAIC_ZARR, ZARR_ATTRS

log = logging.getLogger(__name__)

#: A tile: (row, col).
Tile = tuple[int, int]


@dataclass(frozen=True)
class Realign:
    """Place a second pass's tiles where the first pass's were: the first pass's output
    folder, how many confident tiles make the offset, and the farthest it may be, um; and
    the sharpness (over the first pass's image) below which a tile's one frame taken at its
    prediction is out of focus (`focus_check`; 0: no check)."""

    first_pass: Path
    tiles: int = 4
    max_offset_um: float = 10.0
    min_sharpness_ratio: float = MIN_SHARPNESS_RATIO

    def __post_init__(self) -> None:
        if self.tiles < 1 or not self.max_offset_um > 0:
            raise ValueError(
                f"realign needs at least one tile and a positive bound, got {self.tiles} "
                f"and {self.max_offset_um} um"
            )
        if not 0.0 <= self.min_sharpness_ratio < 1.0:
            raise ValueError(
                f"the sharpness ratio of a frame in focus lies in [0, 1), got "
                f"{self.min_sharpness_ratio}"
            )


def first_pass_mosaic(folder: Path) -> Path:
    """The OME-Zarr mosaic of the first pass's output `folder`; ValueError when it has none
    (checked when the scan's settings are read, and again when the mosaic is opened)."""
    path = Path(folder) / MOSAIC_ZARR
    if not path.exists():
        raise ValueError(
            f"{path} does not exist: --first-pass takes the output folder of a finished scan "
            "whose mosaic is OME-Zarr"
        )
    return path


class FirstPassImages:
    """The first pass's image of each tile's place, cut from its mosaic (OME-Zarr: tiles side
    by side, or stitched in the stage's micrometres where they overlap)."""

    def __init__(self, folder: Path, grid: ScanGrid) -> None:
        import zarr

        path = first_pass_mosaic(folder)
        try:
            root = zarr.open_group(path, mode="r")
            attributes: dict[str, Any] = dict(root.attrs)
            dataset = attributes["ome"]["multiscales"][0]["datasets"][0]
            transforms = {t["type"]: t[t["type"]] for t in dataset["coordinateTransformations"]}
            mosaic = root[dataset["path"]]
            tile_px = attributes[ZARR_ATTRS]["tile_px"]
        except (KeyError, IndexError, TypeError, FileNotFoundError) as error:
            raise ValueError(
                f"{path} is not the mosaic of a FocusTrack scan ({error!r})"
            ) from error
        if not isinstance(mosaic, zarr.Array) or mosaic.ndim != 3:
            raise ValueError(f"{path}: its level 0 is not an image (c, y, x)")
        self.mosaic = mosaic  # (c, y, x), read a window at a time
        self.pixel_um = float(transforms["scale"][-1])
        self.origin_um = (
            float(transforms["translation"][-2]),
            float(transforms["translation"][-1]),
        )
        self.shape = (int(tile_px["height"]), int(tile_px["width"]))
        self.grid = grid
        side_by_side = self.mosaic.shape[-2:] == (
            grid.rows * self.shape[0],
            grid.cols * self.shape[1],
        )
        self.stitched = not (side_by_side and self.origin_um == (0.0, 0.0))

    def tile(self, row: int, col: int) -> np.ndarray | None:
        """The first pass's grey image (height, width) of tile (row, col)'s place; None where
        the mosaic does not hold it whole."""
        height, width = self.shape
        if self.stitched:
            x_um, y_um = self.grid.stage_xy_um(row, col)
            top = round(
                (y_um - (height / 2 - 0.5) * self.pixel_um - self.origin_um[0]) / self.pixel_um
            )
            left = round(
                (x_um - (width / 2 - 0.5) * self.pixel_um - self.origin_um[1]) / self.pixel_um
            )
        else:
            top, left = row * height, col * width
        rows, cols = self.mosaic.shape[-2:]
        if top < 0 or left < 0 or top + height > rows or left + width > cols:
            return None
        window = np.asarray(self.mosaic[:, top : top + height, left : left + width])
        return window.mean(axis=0)


class LateralPlacement:
    """The offset of this pass against the first, from the tiles seen so far (module docstring).

    `observe` takes each tile's image as it is kept; `offset_um` is (x, y) once known, and
    `observe` then hands back the tiles imaged before it, to be taken again at it."""

    def __init__(
        self,
        first: FirstPassImages,
        settings: Realign,
        offset_um: tuple[float, float] | None = None,
    ) -> None:
        self.first = first
        self.settings = settings
        self.offset_um = offset_um
        self._shifts: list[Shift] = []  # of the tiles compared so far
        self._before: dict[Tile, float] = {}  # tiles imaged without the offset -> their z, um

    def sharpness_ratio(self, row: int, col: int, image: np.ndarray) -> float | None:
        """The sharpness of tile (row, col)'s frame `image` (height, width[, channels]) over
        the first pass's image of the tile, on the part both show (`focus_check`); None
        where the first pass's mosaic does not hold the tile, or its place is unknown.

        Once the pass's offset is known the stage went there: the frame shows the first
        pass's place. Before, the tile's own phase correlation places it (None where its
        peak is not confident)."""
        reference = self.first.tile(row, col)
        if reference is None or reference.shape != image.shape[:2]:
            return None
        frame = grey(image)
        shift_px = (0, 0)
        if self.offset_um is None:
            max_shift_px = self.settings.max_offset_um / self.first.pixel_um
            shift = phase_shift(reference, frame, max_shift_px)
            if shift.sharpness < MIN_SHARPNESS:
                return None
            shift_px = (round(shift.dy_px), round(shift.dx_px))
        try:
            return sharpness_ratio(frame, reference, shift_px)
        except ValueError:  # too little of the tile shared to compare
            return None

    def observe(
        self, row: int, col: int, z_um: float, image: np.ndarray
    ) -> list[tuple[int, int, float]]:
        """Tile (row, col)'s image (height, width[, channels]) at `z_um`, kept: the tiles to
        take again (row, col, z um) once this makes the offset known, else none."""
        if self.offset_um is not None:
            return []
        self._before[(row, col)] = z_um
        reference = self.first.tile(row, col)
        if reference is None or reference.shape != image.shape[:2]:
            return []
        max_shift_px = self.settings.max_offset_um / self.first.pixel_um
        self._shifts.append(phase_shift(reference, grey(image), max_shift_px))
        shift = combined(self._shifts, self.settings.tiles)
        if shift is None:
            return []
        self.offset_um = (shift.dx_px * self.first.pixel_um, shift.dy_px * self.first.pixel_um)
        log.info("second pass: lateral offset (%.3f, %.3f) um", *self.offset_um)
        return [(r, c, z) for (r, c), z in self._before.items()]
