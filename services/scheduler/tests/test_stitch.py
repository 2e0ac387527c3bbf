"""Stitching by the stage, refined by the overlaps' cross-correlation within a bound."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.stitch import (
    compose,
    pair_shift,
    pair_shifts,
    place_tiles,
    refine,
    stage_places_px,
    tiles_of_mosaic,
)

SIDE, STEP = 64, 48  # tiles of 64 px, 16 px of overlap
PIXEL_UM = 0.5


def _specimen(seed: int = 0) -> np.ndarray:
    """A textured field (y, x, 3) uint8, larger than any mosaic here."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0, 255, (400, 400))
    kernel = np.ones(3) / 3
    base = np.apply_along_axis(np.convolve, 0, base, kernel, "same")
    base = np.apply_along_axis(np.convolve, 1, base, kernel, "same")
    return np.repeat(base[..., None], 3, axis=2).astype(np.uint8)


def _cut(specimen: np.ndarray, grid: ScanGrid, moved: dict | None = None) -> dict:
    """Tiles cut where the stage says, except those `moved` by (dy, dx) px."""
    tiles = {}
    for (row, col), (y, x) in stage_places_px(grid, PIXEL_UM).items():
        dy, dx = (moved or {}).get((row, col), (0, 0))
        y0, x0 = round(y) + 20 + dy, round(x) + 20 + dx
        tiles[(row, col)] = specimen[y0 : y0 + SIDE, x0 : x0 + SIDE]
    return tiles


GRID = ScanGrid(3, 4, STEP * PIXEL_UM)


def test_tiles_where_the_stage_put_them_have_no_seams() -> None:
    tiles = _cut(_specimen(), GRID)
    placement = place_tiles(tiles, GRID, PIXEL_UM)
    assert len(placement.seam_errors_px) == 3 * 3 + 2 * 4  # every neighbour pair matched
    assert placement.seam_error_px is not None and placement.seam_error_px < 0.3
    mosaic, corner = compose(tiles, stage_places_px(GRID, PIXEL_UM))
    assert corner == (0.0, 0.0)
    np.testing.assert_array_equal(
        mosaic, _specimen()[20 : 20 + 2 * STEP + SIDE, 20 : 20 + 3 * STEP + SIDE]
    )


def test_a_tile_off_its_stage_place_is_found_and_moved_back() -> None:
    tiles = _cut(_specimen(), GRID, {(1, 2): (3, -2)})
    places = stage_places_px(GRID, PIXEL_UM)
    shifts = {(s.a, s.b): s for s in pair_shifts(tiles, places)}
    left = shifts[((1, 1), (1, 2))]
    assert (left.dy_px, left.dx_px) == pytest.approx((3.0, -2.0), abs=0.3)
    refined = refine(places, list(shifts.values()))
    y, x = refined[(1, 2)]
    assert (y - places[(1, 2)][0], x - places[(1, 2)][1]) == pytest.approx((3.0, -2.0), abs=0.3)
    assert refined[(0, 0)] == pytest.approx(places[(0, 0)], abs=1e-9)
    assert max(place_tiles(tiles, GRID, PIXEL_UM).seam_errors_px) < 0.5  # unrefined: 3.6 px


def test_the_refinement_is_bounded_and_glass_says_nothing() -> None:
    places = stage_places_px(GRID, PIXEL_UM)
    blank = np.full((SIDE, SIDE, 3), 200, np.uint8)
    assert pair_shift(blank, blank, (0, STEP)) is None
    tiles = _cut(_specimen(), GRID, {(2, 3): (20, 0)})  # beyond the search: a false match at most
    refined = refine(places, pair_shifts(tiles, places, max_shift_px=4), max_shift_px=4)
    for tile, (y, x) in refined.items():
        assert abs(y - places[tile][0]) <= 4 and abs(x - places[tile][1]) <= 4


def test_tiles_of_a_side_by_side_mosaic() -> None:
    mosaic = np.arange(2 * 3 * 4 * 5 * 3).reshape(2 * 4, 3 * 5, 3)
    tiles = tiles_of_mosaic(mosaic, ScanGrid(2, 3), [(1, 2)])
    np.testing.assert_array_equal(tiles[(1, 2)], mosaic[4:8, 10:15])


def test_the_seams_run_down_the_overlaps_middles_not_a_tiles_edge() -> None:
    """Frames whose outermost pixels are darker (vignetting): pasting whole tiles put each
    tile's dark edge on every seam; the middle of an overlap shows neither's edge."""
    tiles = _cut(_specimen(), GRID)
    edge = 3
    dimmed = {}
    for tile, pixels in tiles.items():
        frame = pixels.astype(np.int16)
        frame[:edge] -= 40
        frame[-edge:] -= 40
        frame[:, :edge] -= 40
        frame[:, -edge:] -= 40
        dimmed[tile] = np.clip(frame, 0, 255).astype(np.uint8)
    mosaic, _ = compose(dimmed, stage_places_px(GRID, PIXEL_UM))
    truth = _specimen()[20 : 20 + 2 * STEP + SIDE, 20 : 20 + 3 * STEP + SIDE]
    inner = np.s_[edge:-edge, edge:-edge]  # the mosaic's own border is a tile's edge
    np.testing.assert_array_equal(mosaic[inner], truth[inner])
    # a tile missing: its neighbours give the whole of their overlaps with its place
    del dimmed[(1, 1)]
    gapped, _ = compose(dimmed, stage_places_px(GRID, PIXEL_UM))
    below_0_1 = np.s_[STEP + 2 : SIDE - edge, SIDE : 2 * STEP]  # (0, 1)'s, past its half
    np.testing.assert_array_equal(gapped[below_0_1], truth[below_0_1])
