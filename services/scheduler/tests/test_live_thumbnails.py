"""The live view's thumbnail mosaic: each tile small, in its cell, at its stage position."""

from __future__ import annotations

import io

import numpy as np
import pytest
from matplotlib.image import imread

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.thumbnails import MAX_CELL_PX, MAX_SIDE_PX, Thumbnails, shrink


def test_shrinking_averages_each_block() -> None:
    image = np.arange(16, dtype=np.uint8).reshape(4, 4, 1)
    assert shrink(image, 2, 2)[..., 0].tolist() == [[2, 4], [10, 12]]  # 2.5 and 4.5 round even
    assert shrink(image, 8, 8).shape == (4, 4, 1)  # never larger than the image


def test_overlapping_tiles_show_their_middle_pitch_and_meet_without_gaps() -> None:
    grid = ScanGrid(2, 3, pitch_um=90.0)
    thumbnails = Thumbnails(grid)
    cell = thumbnails.cell_px
    assert cell == MAX_CELL_PX  # a small grid: the largest cells
    tile = np.zeros((100, 100, 3), np.uint8)  # 100 px of 1 um: 10 um shared with each neighbour
    tile[:5] = 255  # a bright strip in the overlap above: not shown
    tile[5:95, 5:95] = (10, 120, 200)
    thumbnails.put(1, 2, tile, pixel_um=1.0)
    placed = thumbnails.rgba[cell : 2 * cell, 2 * cell : 3 * cell]
    assert (placed == (10, 120, 200, 255)).all()  # the middle 90 um fills the cell exactly
    assert (thumbnails.rgba[:cell] == 0).all()  # row 0: not kept yet, transparent
    assert thumbnails.version == 1


def test_tiles_apart_fill_their_cells_and_grey_tiles_stay_grey() -> None:
    grid = ScanGrid(4, 4, pitch_um=200.0)
    thumbnails = Thumbnails(grid)
    cell = thumbnails.cell_px
    tile = np.full((100, 50, 1), 40, np.uint8)  # one channel, 50 x 25 um: far apart
    tile[:, :25] = 100
    thumbnails.put(0, 1, tile, pixel_um=0.5)
    placed = thumbnails.rgba[:cell, cell : 2 * cell]
    assert (placed[..., 3] == 255).all()
    assert (placed[:, : cell // 4] == 255).all() and (placed[:, -cell // 4 :] == 255).all()
    assert (placed[:, cell // 4 : cell // 2, :3] == 100).all()  # the tile's left half
    assert (placed[:, cell // 2 : 3 * cell // 4, :3] == 40).all()  # grey in all channels


def test_the_mosaic_stays_small_on_a_large_grid_and_is_encoded_once_per_change() -> None:
    grid = ScanGrid(200, 200)
    thumbnails = Thumbnails(grid)
    assert max(thumbnails.rgba.shape[:2]) <= MAX_SIDE_PX
    assert thumbnails.rgba.nbytes <= MAX_SIDE_PX**2 * 4
    thumbnails.put(199, 0, np.full((512, 512, 3), 90, np.uint8), pixel_um=0.4)
    first = thumbnails.png()
    assert thumbnails.png() is first  # unchanged: not encoded again
    decoded = imread(io.BytesIO(first))
    assert decoded.shape == thumbnails.rgba.shape
    cell = thumbnails.cell_px
    assert decoded[-1, 0] == pytest.approx([90 / 255] * 3 + [1.0], abs=1e-6)
    assert decoded[0, 0, 3] == 0.0
    thumbnails.put(0, 0, np.full((512, 512, 3), 90, np.uint8), pixel_um=0.4)
    assert imread(io.BytesIO(thumbnails.png()))[cell // 2, cell // 2, 3] == 1.0
