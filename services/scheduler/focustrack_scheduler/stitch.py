"""Stitching by the stage: tiles placed where the stage put them, refined by the overlaps'
cross-correlation within a bound. Pure functions over numpy arrays.

A tile's place comes first from its stage position (`ScanGrid.stage_xy_um`, over the pixel
size). Where neighbours overlap (a virtual slide's tiles share `overlap` of their side),
the shift that best aligns the shared strip (`pair_shift`: normalised cross-correlation,
searched over +/- `max_shift_px`, refined below a pixel by a parabola) says how far the
stage's placement is off for that pair; a strip with no texture (empty glass) or no match
(correlation below `MIN_CORRELATION`) says nothing and is left out, and a shift that
matches hardly better than the stage's place (`MIN_GAIN`) is not taken. The search
reaches a third of the overlap at most, so that two thirds of it are compared at every
shift. `refine` then moves every tile by the least-squares solution of all pairs' shifts
(the first tile held still, false matches left out), each move bounded by
`max_shift_px`: a wrong match can pull a tile no further than that. `place_tiles` gives
the places and what remains, the seams' errors: per pair, the shift still measured at the
refined places (0 where the overlaps agree).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.lateral import grey, parabola_vertex

#: A tile: (row, col).
Tile = tuple[int, int]

#: The search's bound, px: a stage is off by a few um at most.
MAX_SHIFT_PX = 8
#: A strip whose grey std is below this share of its mean has no texture to match.
MIN_TEXTURE = 0.01
#: A match below this normalised correlation is no match.
MIN_CORRELATION = 0.5
#: A shift is taken where it correlates better than the stage's place by this much; else
#: the content matches about as well anywhere (smooth, or stripes along the shift) and the
#: stage's place stands.
MIN_GAIN = 0.05
#: A pair whose shift the least-squares places miss by more than this (px) is a false match.
OUTLIER_PX = 2.0


@dataclass(frozen=True)
class PairShift:
    """How far tile `b` must move (dy, dx px) from its stage place to match tile `a`, and the
    peak normalised correlation of the match."""

    a: Tile
    b: Tile
    dy_px: float
    dx_px: float
    correlation: float


def stage_places_px(grid: ScanGrid, pixel_um: float) -> dict[Tile, tuple[float, float]]:
    """Every tile's top-left corner (y, x) in pixels from tile (0, 0)'s, by the stage."""
    x0_um, y0_um = grid.stage_xy_um(0, 0)
    places = {}
    for row in range(grid.rows):
        for col in range(grid.cols):
            x_um, y_um = grid.stage_xy_um(row, col)
            places[(row, col)] = ((y_um - y0_um) / pixel_um, (x_um - x0_um) / pixel_um)
    return places


def tiles_of_mosaic(
    mosaic: np.ndarray, grid: ScanGrid, kept: Iterable[Tile]
) -> dict[Tile, np.ndarray]:
    """The `kept` tiles of a mosaic whose tiles lie side by side (h, w, c each, the scan's
    partial mosaic: `mosaic_store.MosaicStore`)."""
    height, width = mosaic.shape[0] // grid.rows, mosaic.shape[1] // grid.cols
    return {
        (row, col): np.asarray(
            mosaic[row * height : (row + 1) * height, col * width : (col + 1) * width]
        )
        for row, col in kept
    }


def pair_shift(
    a: np.ndarray,
    b: np.ndarray,
    offset_px: tuple[int, int],
    max_shift_px: int = MAX_SHIFT_PX,
) -> tuple[float, float, float] | None:
    """The shift (dy, dx, correlation) of tile `b` (h, w[, c]) placed at `offset_px` (its
    corner from `a`'s, whole pixels) that best matches `a` over their overlap, searched
    within +/- `max_shift_px` (and a third of the overlap); None where the overlap is too
    small, has no texture or nothing matches."""
    ga, gb = grey(a), grey(b)
    height, width = ga.shape
    oy, ox = offset_px
    m = min(max_shift_px, (height - abs(oy)) // 3, (width - abs(ox)) // 3)
    # the part of a's pixels that b covers at every shift searched
    y0, y1 = max(0, oy + m), min(height, oy + height - m)
    x0, x1 = max(0, ox + m), min(width, ox + width - m)
    if m < 1 or y1 - y0 < 4 or x1 - x0 < 4:
        return None
    strip = ga[y0:y1, x0:x1]
    if strip.std() < MIN_TEXTURE * max(float(strip.mean()), 1e-9):
        return None
    strip = (strip - strip.mean()) / strip.std()
    scores = np.full((2 * m + 1, 2 * m + 1), -np.inf)
    for i, dy in enumerate(range(-m, m + 1)):
        for j, dx in enumerate(range(-m, m + 1)):
            # b's pixel (y - oy - dy, x - ox - dx) lies over a's (y, x) when b moves by (dy, dx)
            window = gb[y0 - oy - dy : y1 - oy - dy, x0 - ox - dx : x1 - ox - dx]
            std = window.std()
            if std > 0:
                scores[i, j] = float(np.mean(strip * (window - window.mean()) / std))
    top_i, top_j = (int(k) for k in np.unravel_index(int(np.argmax(scores)), scores.shape))
    best = float(scores[top_i, top_j])
    if best < MIN_CORRELATION:  # noise on glass, or nothing alike: the overlap says nothing
        return None
    if best - float(scores[m, m]) < MIN_GAIN:  # smooth content matches anywhere: the stage's
        return 0.0, 0.0, float(scores[m, m])
    shift_y, shift_x = float(top_i - m), float(top_j - m)
    if 0 < top_i < 2 * m:
        shift_y += parabola_vertex(scores[top_i - 1, top_j], best, scores[top_i + 1, top_j])
    if 0 < top_j < 2 * m:
        shift_x += parabola_vertex(scores[top_i, top_j - 1], best, scores[top_i, top_j + 1])
    return shift_y, shift_x, best


def pair_shifts(
    tiles: Mapping[Tile, np.ndarray],
    places_px: Mapping[Tile, tuple[float, float]],
    max_shift_px: int = MAX_SHIFT_PX,
) -> list[PairShift]:
    """The shift of every right and lower neighbour pair of `tiles` at `places_px` whose
    overlap can be matched (`pair_shift`)."""
    found = []
    for (row, col), image in tiles.items():
        for other in ((row, col + 1), (row + 1, col)):
            if other not in tiles:
                continue
            (ay, ax), (by, bx) = places_px[(row, col)], places_px[other]
            offset = (round(by - ay), round(bx - ax))
            # the places' fractions of a pixel, matched as part of the shift
            rest = (by - ay - offset[0], bx - ax - offset[1])
            shift = pair_shift(image, tiles[other], offset, max_shift_px)
            if shift is not None:
                dy, dx, correlation = shift
                found.append(PairShift((row, col), other, dy - rest[0], dx - rest[1], correlation))
    return found


def refine(
    places_px: Mapping[Tile, tuple[float, float]],
    shifts: list[PairShift],
    max_shift_px: int = MAX_SHIFT_PX,
) -> dict[Tile, tuple[float, float]]:
    """The places moved by the least-squares solution of the pairs' shifts (each tile's move
    bounded by `max_shift_px`; a tile in no pair, and the first tile, stay). Pairs that
    disagree with the solution by more than `OUTLIER_PX` (a false match) are left out and
    the rest solved again."""
    order = sorted(places_px)
    index = {tile: k for k, tile in enumerate(order)}
    if not shifts:
        return dict(places_px)
    rows = np.zeros((len(shifts) + 1, len(order)))
    targets = np.zeros((len(shifts) + 1, 2))
    for k, pair in enumerate(shifts):
        rows[k, index[pair.b]] += 1.0
        rows[k, index[pair.a]] -= 1.0
        targets[k] = (pair.dy_px, pair.dx_px)
    rows[-1, 0] = 1.0  # the first tile holds still
    moves, *_ = np.linalg.lstsq(rows, targets, rcond=None)
    kept = np.hypot(*(rows @ moves - targets).T) <= OUTLIER_PX
    moves, *_ = np.linalg.lstsq(rows[kept], targets[kept], rcond=None)
    moves = np.clip(moves, -max_shift_px, max_shift_px)
    return {
        tile: (y + float(moves[index[tile], 0]), x + float(moves[index[tile], 1]))
        for tile, (y, x) in places_px.items()
    }


@dataclass(frozen=True)
class Placement:
    """Where the kept tiles lie: each one's corner (y, x) in px from tile (0, 0)'s stage
    place, refined (`refine`); and the seams' errors: per matched neighbour pair, how far
    (px) its overlaps still disagree at those places."""

    places_px: dict[Tile, tuple[float, float]]
    seam_errors_px: tuple[float, ...]

    @property
    def seam_error_px(self) -> float | None:
        """The RMS of the seams' errors (None without a matched pair)."""
        if not self.seam_errors_px:
            return None
        return float(np.sqrt(np.mean(np.square(self.seam_errors_px))))


def overlapping(grid: ScanGrid, tile_width_px: int, pixel_um: float) -> bool:
    """Whether neighbouring tiles share pixels (the pitch is below a tile's width)."""
    return grid.pitch_um < tile_width_px * pixel_um


def place_tiles(
    tiles: Mapping[Tile, np.ndarray],
    grid: ScanGrid,
    pixel_um: float,
    max_shift_px: int = MAX_SHIFT_PX,
) -> Placement:
    """The tiles placed by the stage and refined by their overlaps (see `Placement`)."""
    stage = stage_places_px(grid, pixel_um)
    refined = refine(stage, pair_shifts(tiles, stage, max_shift_px), max_shift_px)
    kept = {tile: refined[tile] for tile in tiles}
    errors = tuple(
        float(np.hypot(s.dy_px, s.dx_px)) for s in pair_shifts(tiles, refined, max_shift_px)
    )
    return Placement(kept, errors)


def compose(
    tiles: Mapping[Tile, np.ndarray],
    places_px: Mapping[Tile, tuple[float, float]],
    canvas_tiles: Iterable[Tile] | None = None,
    fill: float = 0,
) -> tuple[np.ndarray, tuple[float, float]]:
    """The mosaic of `tiles` (h, w, ... each) at their places (rounded to whole pixels),
    `fill` where no tile lies, and the place (y, x px) of its corner relative to tile
    (0, 0)'s.

    Where neighbours overlap, each gives the half of the overlap nearer its own centre, so
    the seams run down the overlaps' middles: a frame's outermost pixels (a camera's
    vignetting, a lens' edge) differ from the same place seen in the middle of the next
    frame, and pasting whole tiles put that step on every seam. Each tile is pasted whole
    first, so a place no neighbour's half reaches (a missing tile, a stage's jitter)
    still shows it.

    The mosaic spans `canvas_tiles` (by default `tiles` themselves), all of the same size:
    a layer of some tiles (their phase) then lies pixel for pixel over the mosaic of all
    (their images)."""
    first = next(iter(tiles.values()))
    height, width = first.shape[:2]
    spanned = list(tiles if canvas_tiles is None else canvas_tiles)
    corners = {
        tile: (round(places_px[tile][0]), round(places_px[tile][1])) for tile in {*spanned, *tiles}
    }
    y0 = min(corners[tile][0] for tile in spanned)
    x0 = min(corners[tile][1] for tile in spanned)
    y1 = max(corners[tile][0] for tile in spanned) + height
    x1 = max(corners[tile][1] for tile in spanned) + width
    mosaic = np.full((y1 - y0, x1 - x0, *first.shape[2:]), fill, dtype=first.dtype)
    for tile in sorted(tiles):
        y, x = corners[tile]
        mosaic[y - y0 : y - y0 + height, x - x0 : x - x0 + width] = tiles[tile]
    present = set(tiles)
    for tile in sorted(tiles):
        y, x = corners[tile]
        top, bottom, left, right = _own_part(tile, corners, present, height, width)
        mosaic[y - y0 + top : y - y0 + bottom, x - x0 + left : x - x0 + right] = tiles[tile][
            top:bottom, left:right
        ]
    return mosaic, (float(y0), float(x0))


def _own_part(
    tile: Tile,
    corners: Mapping[Tile, tuple[int, int]],
    present: set[Tile],
    height: int,
    width: int,
) -> tuple[int, int, int, int]:
    """The rows [top, bottom) and columns [left, right) of `tile` (px of the tile) nearer its
    centre than its grid neighbours' among `present`: each side ends at the middle of the
    overlap with the neighbour there (the tile's edge where it has none or they do not
    overlap)."""
    row, col = tile
    y, x = corners[tile]
    top, bottom, left, right = 0, height, 0, width
    if (up := (row - 1, col)) in present:
        top = max(top, min(height, (corners[up][0] + height - y) // 2))
    if (down := (row + 1, col)) in present:
        bottom = min(bottom, max(0, (corners[down][0] - y + height) // 2))
    if (before := (row, col - 1)) in present:
        left = max(left, min(width, (corners[before][1] + width - x) // 2))
    if (after := (row, col + 1)) in present:
        right = min(right, max(0, (corners[after][1] - x + width) // 2))
    return top, max(top, bottom), left, max(left, right)
