"""The live view's mosaic of tile thumbnails: each kept tile, small, at its stage position.

One RGBA image of the whole grid, `cell_px` pixels per pitch (`ScanGrid.pitch_um`), so its
cells line up with the maps' tiles: cell (row, col) is centred on the tile's stage
position. Where tiles overlap (a virtual slide's), a cell shows the middle `pitch_um` of
its tile, so neighbours meet without seams and the mosaic is to the stage's scale; where
they lie apart (fields far smaller than the pitch), a cell shows its whole tile, enlarged
to fill it (at the stage's scale it would be a dot), on white (glass) where the tile is
not square. Cells of tiles not yet kept are transparent. Memory is bounded whatever the
grid: the image is at most `MAX_SIDE_PX` on its longest side (one pixel per tile beyond
that many tiles).
"""

from __future__ import annotations

import io
import threading

import numpy as np

from focustrack_core.geometry import ScanGrid

#: Longest side of the thumbnail mosaic, px (200x200 tiles: 6 px each, 1200 px, 5.8 MB RGBA).
MAX_SIDE_PX = 1280
#: Side of one tile's cell at most, px (a small grid's thumbnails stay thumbnails).
MAX_CELL_PX = 64
#: A tile is read at most this many times the thumbnail's side before it is averaged down
#: (a strided read of the memory-mapped mosaic: a few rows of each tile, not all of them).
OVERSAMPLE = 4
#: What a kept tile's cell shows outside its image: glass.
GLASS_RGBA = (255, 255, 255, 255)


def shrink(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """`image` (h, w, channels) as (height, width, channels): each pixel the mean of the
    block of `image` it covers (no aliasing); at most the image's own size."""
    height, width = min(height, image.shape[0]), min(width, image.shape[1])
    rows = np.linspace(0, image.shape[0], height + 1).astype(int)
    cols = np.linspace(0, image.shape[1], width + 1).astype(int)
    sums = np.add.reduceat(
        np.add.reduceat(image.astype(np.float32), rows[:-1], axis=0), cols[:-1], axis=1
    )
    counts = np.outer(np.diff(rows), np.diff(cols))[..., None]
    return np.rint(sums / counts).astype(image.dtype)


def as_rgb(image: np.ndarray) -> np.ndarray:
    """A tile (h, w, channels) as (h, w, 3): its first three channels, or its first one grey."""
    return image[..., :3] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=2)


def encode_png(rgba: np.ndarray) -> bytes:
    """`rgba` (h, w, 4) uint8 as a PNG, pixel for pixel; the fastest compression (about 60
    ms for a 200x200 grid's 1200 px, a third of the default's), as it is encoded again while
    the scan runs and served on loopback or a lab's network."""
    from matplotlib.image import imsave  # only a view that shows thumbnails needs it

    buffer = io.BytesIO()
    imsave(buffer, rgba, format="png", pil_kwargs={"compress_level": 1})
    return buffer.getvalue()


class Thumbnails:
    """The thumbnail mosaic of one scan (module docstring); `put` on the scanning thread,
    `png` on the server's, each under the lock."""

    def __init__(self, grid: ScanGrid, max_side_px: int = MAX_SIDE_PX) -> None:
        self.grid = grid
        self.cell_px = int(np.clip(max_side_px // max(grid.rows, grid.cols), 1, MAX_CELL_PX))
        self.rgba = np.zeros((grid.rows * self.cell_px, grid.cols * self.cell_px, 4), np.uint8)
        self.version = 0  # bumped by every `put`
        self._png: tuple[int, bytes] | None = None  # the last encoding and its version
        self._lock = threading.Lock()

    def put(self, row: int, col: int, image: np.ndarray, pixel_um: float) -> None:
        """Tile (row, col)'s image (h, w, channels) uint8, `pixel_um` wide pixels, in its cell."""
        cell = self.cell_px
        pitch_px = max(1, round(self.grid.pitch_um / pixel_um))  # a tile's pixels in its cell
        h, w = min(image.shape[0], pitch_px), min(image.shape[1], pitch_px)
        y0, x0 = (image.shape[0] - h) // 2, (image.shape[1] - w) // 2
        scale = cell / max(h, w)  # the longer side fills the cell
        ny, nx = max(1, round(h * scale)), max(1, round(w * scale))
        step = max(1, min(h // (OVERSAMPLE * ny), w // (OVERSAMPLE * nx)))
        crop = np.asarray(image[y0 : y0 + h : step, x0 : x0 + w : step])
        small = shrink(as_rgb(crop), ny, nx)
        top, left = (
            row * cell + (cell - small.shape[0]) // 2,
            col * cell + (cell - small.shape[1]) // 2,
        )
        with self._lock:
            self.rgba[row * cell : (row + 1) * cell, col * cell : (col + 1) * cell] = GLASS_RGBA
            self.rgba[top : top + small.shape[0], left : left + small.shape[1], :3] = small
            self.version += 1

    def png(self) -> bytes:
        """The mosaic as a PNG, encoded again only when a tile was put since the last one."""
        with self._lock:
            if self._png is not None and self._png[0] == self.version:
                return self._png[1]
            version, rgba = self.version, self.rgba.copy()
        png = encode_png(rgba)
        with self._lock:
            self._png = (version, png)
        return png
