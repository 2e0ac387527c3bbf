"""A continuous virtual slide: one H&E-stained tissue section per seed, cut into tiles that
overlap, under a coverslip that carries dust.

Everything is drawn in slide coordinates (um; x along columns, y along rows, tile (0, 0)
centred at the origin, as `ScanGrid.stage_xy_um`), so a tile is a window of one specimen:
neighbours share `overlap` of their side, pixel for pixel, and a mosaic placed by the stage
positions has no seams. Objects are drawn from blocks of `BLOCK_UM` whose seeds depend on the
slide's seed and the block alone, so a tile draws the same cells whichever tile asks.

- The section: an irregular outline (an ellipse bent by low-frequency waves) with holes
  (tears, vessels) and empty glass around it; inside, eosin-pink stroma with fibres, cells
  (pink cytoplasm) with hematoxylin-purple nuclei and their chromatin. Optical densities
  per channel as `specimen` uses them (Beer-Lambert).
- Heights: the section follows a surface of the core's map families (`generate_surface`,
  per tile), plus the slide's tilt; the coverslip's upper face (where dust settles) lies
  10-170 um above the section (the coverslip's thickness), wedged: its height above the
  section changes linearly across the slide.
- Folds: bands where the section lies twice, the second layer a few um above the first.
- Dust and debris: specks and fibres on the coverslip; bubbles: dark-rimmed discs in the
  same plane (the mountant under it is not modelled apart).

`TissueSlide.tile` gives a tile's layers (transmissions and their heights above the
section); `TissueSlide.truth` what evaluation needs per tile: tissue share, empty, dust and
fold heights.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_core.surfaces import SurfaceSpec, generate_surface
from focustrack_instrument_sim.microscope import Slide
from focustrack_instrument_sim.specimen import _Canvas

#: Side of the blocks objects are drawn from, um.
BLOCK_UM = 40.0
#: The fold's upper layer shows the section this far away (along y), um.
FOLD_SHIFT_UM = 5000.0
#: A tile with less tissue than this share of its area is empty glass.
EMPTY_BELOW = 0.002

# Optical density (R, G, B) of the H&E stains at full thickness.
_EOSIN_OD = np.array([0.05, 0.5, 0.18], dtype=np.float32)
_HEMATOXYLIN_OD = np.array([0.55, 0.62, 0.22], dtype=np.float32)
_GLASS_OD = np.array([0.01, 0.012, 0.01], dtype=np.float32)
_DUST_OD = np.array([0.9, 0.9, 0.9], dtype=np.float32)
_BUBBLE_RIM_OD = np.array([0.45, 0.45, 0.45], dtype=np.float32)


@dataclass(frozen=True)
class TissueSlideSpec:
    """The section and its coverslip. Lengths in um, densities per mm^2, slopes um per mm."""

    overlap: float = 0.1  # share of a tile's side that its neighbour shares
    nucleus_density: float = 6000.0
    dust_density: float = 120.0  # specks and fibres on the coverslip
    bubbles: int = 1
    folds: int = 1
    fold_dz_um: tuple[float, float] = (2.0, 5.0)
    fold_width_um: tuple[float, float] = (8.0, 25.0)
    fold_length_um: tuple[float, float] = (40.0, 150.0)
    coverslip_above_um: tuple[float, float] = (10.0, 170.0)
    tilt_um_per_mm: float = 3.0  # std of each of the slide's two slopes
    wedge_um_per_mm: float = 2.0  # std of each slope of the coverslip against the section
    hole_share: float = 0.08  # of the outline's area
    edge_um: float = 0.25

    def __post_init__(self) -> None:
        if not 0.0 <= self.overlap < 0.5:
            raise ValueError(f"overlap must be in [0, 0.5), got {self.overlap}")
        low, high = self.coverslip_above_um
        if not 0.0 < low <= high:
            raise ValueError(f"coverslip_above_um must be 0 < low <= high, got {(low, high)}")


@dataclass(frozen=True)
class TissueTile:
    """A tile's layers: transmission (height, width, 3) float32 of the section; of the fold's
    upper layer (1 where there is none) and its height above the section, um; the dust
    plane's grey transmission (height, width) and its height above the section, um."""

    section: np.ndarray
    fold: np.ndarray | None
    fold_dz_um: float
    dust: np.ndarray
    dust_dz_um: float


@dataclass(frozen=True)
class TileTruth:
    """Per tile, (rows, cols): tissue share of its area; empty (share below EMPTY_BELOW);
    height of its dust above the section, um (NaN: no dust in view); height of a fold's
    upper layer above the section, um (NaN: no fold)."""

    tissue_share: np.ndarray
    empty: np.ndarray
    dust_dz_um: np.ndarray
    fold_dz_um: np.ndarray


class _Waves:
    """A smooth random field of slide coordinates: a sum of cosines of random directions
    and phases at wavelengths around `wavelength_um`, std about 1."""

    def __init__(self, rng: np.random.Generator, wavelength_um: float, n: int = 8) -> None:
        angles = rng.uniform(0.0, np.pi, n)
        k = 2.0 * np.pi / (wavelength_um * rng.uniform(0.7, 1.4, n))
        self.ky, self.kx = k * np.sin(angles), k * np.cos(angles)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, n)
        self.scale = math.sqrt(2.0 / n)

    def __call__(self, y_um: np.ndarray, x_um: np.ndarray) -> np.ndarray:
        total = np.zeros(np.broadcast_shapes(y_um.shape, x_um.shape), dtype=np.float32)
        for ky, kx, phase in zip(self.ky, self.kx, self.phase, strict=True):
            total += np.cos(ky * y_um + kx * x_um + phase).astype(np.float32)
        return total * np.float32(self.scale)


@dataclass(frozen=True)
class _Band:
    """A fold: the band within `half_width_um` of a segment through (y, x) at `angle`,
    `half_length_um` long each way."""

    y_um: float
    x_um: float
    angle: float
    half_width_um: float
    half_length_um: float
    dz_um: float

    def distance_um(self, y_um: np.ndarray, x_um: np.ndarray) -> np.ndarray:
        """How far each point lies from the segment, um."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        across = (y_um - self.y_um) * c - (x_um - self.x_um) * s
        along = (y_um - self.y_um) * s + (x_um - self.x_um) * c
        beyond = np.clip(np.abs(along) - self.half_length_um, 0.0, None)
        return np.hypot(across, beyond)


@dataclass(frozen=True, eq=False)
class TissueSlide(Slide):
    """A `Slide` whose tiles are windows of one tissue section (see the module docstring).

    `focus_um` (rows, cols) is the section's height under each tile centre; `dust_above_um`
    (rows, cols) the coverslip's upper face above it. `tile_um` is a tile's side (height,
    width) in um; the grid's pitch is its width less the overlap.
    """

    tile_um: tuple[float, float] = (0.0, 0.0)
    dust_above_um: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    spec: TissueSlideSpec = field(default_factory=TissueSlideSpec)

    def _rng(self, *key: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([*self.specimen_seed, *key]))

    @property
    def _extent_um(self) -> tuple[float, float, float, float]:
        """(y0, x0, y1, x1) of the scanned area, um."""
        height, width = self.tile_um
        return (
            -height / 2,
            -width / 2,
            (self.grid.rows - 1) * self.grid.pitch_um + height / 2,
            (self.grid.cols - 1) * self.grid.pitch_um + width / 2,
        )

    @functools.cached_property
    def _shape_fields(self) -> tuple[_Waves, _Waves, _Waves, list[_Band]]:
        """The outline's and holes' fields, the fibres' and the folds."""
        rng = self._rng(1)
        y0, x0, y1, x1 = self._extent_um
        size_um = max(y1 - y0, x1 - x0)
        outline = _Waves(rng, size_um / 1.5, 6)
        holes = _Waves(rng, 90.0, 8)
        fibres = _Waves(rng, 3.0, 12)
        bands = []
        for _ in range(self.spec.folds):
            bands.append(
                _Band(
                    float(rng.uniform(y0, y1)),
                    float(rng.uniform(x0, x1)),
                    float(rng.uniform(0.0, np.pi)),
                    float(rng.uniform(*self.spec.fold_width_um)) / 2,
                    float(rng.uniform(*self.spec.fold_length_um)) / 2,
                    float(rng.uniform(*self.spec.fold_dz_um)),
                )
            )
        return outline, holes, fibres, bands

    def tissue_mask(self, y_um: np.ndarray, x_um: np.ndarray) -> np.ndarray:
        """1 where the section lies at these slide coordinates (um), 0 on glass; soft edges."""
        outline, holes, _, _ = self._shape_fields
        y0, x0, y1, x1 = self._extent_um
        cy, cx, ry, rx = (y0 + y1) / 2, (x0 + x1) / 2, (y1 - y0) * 0.45, (x1 - x0) * 0.45
        inside = 1.0 - np.hypot((y_um - cy) / ry, (x_um - cx) / rx) + 0.25 * outline(y_um, x_um)
        # a hole where the fine field is high: its threshold leaves `hole_share` of the area
        hole_level = math.sqrt(2.0) * _erfinv(1.0 - 2.0 * self.spec.hole_share)
        hole = holes(y_um, x_um) - hole_level
        mask = np.clip(inside / 0.03, 0.0, 1.0) * np.clip(-hole / 0.1, 0.0, 1.0)
        return mask.astype(np.float32)

    def _tile_origin_um(self, row: int, col: int) -> tuple[float, float]:
        x_um, y_um = self.grid.stage_xy_um(row, col)
        height, width = self.tile_um
        return y_um - self.grid.origin_y_um - height / 2, x_um - self.grid.origin_x_um - width / 2

    def _blocks(self, y0: float, x0: float, y1: float, x1: float, reach_um: float):
        """(block row, block col) of every block within `reach_um` of the window."""
        for by in range(
            math.floor((y0 - reach_um) / BLOCK_UM), math.floor((y1 + reach_um) / BLOCK_UM) + 1
        ):
            for bx in range(
                math.floor((x0 - reach_um) / BLOCK_UM), math.floor((x1 + reach_um) / BLOCK_UM) + 1
            ):
                yield by, bx

    def _nuclei(self, by: int, bx: int) -> list[tuple[float, float, float, float, float, float]]:
        """(y, x, radius, aspect, angle, cytoplasm radius) of every candidate nucleus of a
        block, slide um (those off the section are dropped by the caller)."""
        rng = self._rng(2, by + 1_000_000, bx + 1_000_000)
        n = rng.poisson(self.spec.nucleus_density * (BLOCK_UM / 1000.0) ** 2)
        points = rng.uniform(0.0, BLOCK_UM, (n, 2)) + np.array([by, bx]) * BLOCK_UM
        return [
            (
                float(y),
                float(x),
                float(rng.uniform(2.2, 4.0)),
                float(rng.uniform(1.0, 1.8)),
                float(rng.uniform(0.0, np.pi)),
                float(rng.uniform(4.0, 7.0)),
            )
            for y, x in points
        ]

    def _specks(self, by: int, bx: int) -> list[tuple[float, float, float, float, float]]:
        """(y, x, radius, aspect, angle) of the dust of a coverslip block, slide um: specks
        of 0.5-3 um and a few fibres of debris (long, thin)."""
        rng = self._rng(3, by + 1_000_000, bx + 1_000_000)
        n = rng.poisson(self.spec.dust_density * (BLOCK_UM / 1000.0) ** 2)
        specks = []
        for y, x in rng.uniform(0.0, BLOCK_UM, (n, 2)) + np.array([by, bx]) * BLOCK_UM:
            fibre = rng.uniform() < 0.2
            radius = rng.uniform(0.4, 1.2) if fibre else rng.uniform(0.5, 3.0)
            aspect = rng.uniform(8.0, 25.0) if fibre else rng.uniform(1.0, 2.0)
            specks.append(
                (float(y), float(x), float(radius), float(aspect), float(rng.uniform(0, np.pi)))
            )
        return specks

    def _bubbles(self) -> list[tuple[float, float, float]]:
        """(y, x, radius) of the bubbles, slide um."""
        rng = self._rng(4)
        y0, x0, y1, x1 = self._extent_um
        return [
            (float(rng.uniform(y0, y1)), float(rng.uniform(x0, x1)), float(rng.uniform(15.0, 45.0)))
            for _ in range(self.spec.bubbles)
        ]

    def _section_od(
        self, y0: float, x0: float, shape: tuple[int, int], pixel_um: float, everywhere: bool
    ) -> np.ndarray:
        """Optical density (height, width, 3) of the section over a window whose corner is
        at (y0, x0), um; `everywhere`: as if the section covered the whole slide."""
        _, _, fibres, _ = self._shape_fields
        canvas = _Canvas(shape, pixel_um, self.spec.edge_um)
        yy = (y0 + (np.arange(shape[0]) + 0.5) * pixel_um)[:, None]
        xx = (x0 + (np.arange(shape[1]) + 0.5) * pixel_um)[None, :]
        mask = np.ones((1, 1), np.float32) if everywhere else self.tissue_mask(yy, xx)
        # stroma: pink, with fibres (the fine waves, sharpened) over a base of cytoplasm
        fibre = np.clip(fibres(yy, xx), 0.0, None) ** 2
        canvas.od += (mask * (0.45 + 0.35 * fibre))[..., None] * _EOSIN_OD
        y1, x1 = y0 + shape[0] * pixel_um, x0 + shape[1] * pixel_um
        cells = np.array(
            [cell for block in self._blocks(y0, x0, y1, x1, 8.0) for cell in self._nuclei(*block)]
        ).reshape(-1, 6)
        if not everywhere and len(cells):
            cells = cells[self.tissue_mask(cells[:, 0], cells[:, 1]) > 0.5]
        for y, x, radius, aspect, angle, cytoplasm in cells:
            cy, cx = y - y0, x - x0
            canvas.ellipse(cy, cx, cytoplasm, 0.35 * _EOSIN_OD)
            canvas.ellipse(cy, cx, radius, _HEMATOXYLIN_OD, aspect=aspect, angle=angle)
            for k in range(3):  # chromatin: darker clumps inside
                a = angle + 2.1 * k
                dy, dx = 0.45 * radius * math.sin(a), 0.45 * radius * math.cos(a)
                canvas.ellipse(cy + dy, cx + dx, 0.35 * radius, 0.5 * _HEMATOXYLIN_OD)
        return canvas.od + _GLASS_OD

    def tile(
        self,
        row: int,
        col: int,
        shape: tuple[int, int],
        pixel_um: float,
        view_um: tuple[float, float] = (0.0, 0.0),
    ) -> TissueTile:
        """The layers of tile (row, col) as a camera of `shape` pixels of `pixel_um` sees it,
        its window moved by `view_um` (y, x) on the slide (a stage off the tile's place)."""
        y0, x0 = self._tile_origin_um(row, col)
        y0, x0 = y0 + view_um[0], x0 + view_um[1]
        section = np.exp(-self._section_od(y0, x0, shape, pixel_um, False))
        yy = (y0 + (np.arange(shape[0]) + 0.5) * pixel_um)[:, None]
        xx = (x0 + (np.arange(shape[1]) + 0.5) * pixel_um)[None, :]
        fold = None
        fold_dz_um = 0.0
        for band in self._shape_fields[3]:
            inside = np.clip((band.half_width_um - band.distance_um(yy, xx)) / 1.0, 0.0, 1.0)
            inside *= self.tissue_mask(yy, xx)  # a fold of the section lies on the section
            if inside.max() > 0.5:  # the upper layer: tissue from elsewhere, folded over
                od = self._section_od(y0 + FOLD_SHIFT_UM, x0, shape, pixel_um, True)
                upper = od * inside[..., None]
                fold, fold_dz_um = np.exp(-upper), band.dz_um
                break
        return TissueTile(
            section.astype(np.float32),
            None if fold is None else fold.astype(np.float32),
            fold_dz_um,
            self._dust(y0, x0, shape, pixel_um),
            float(self.dust_above_um[row, col]),
        )

    def _dust(self, y0: float, x0: float, shape: tuple[int, int], pixel_um: float) -> np.ndarray:
        canvas = _Canvas(shape, pixel_um, 0.4)
        y1, x1 = y0 + shape[0] * pixel_um, x0 + shape[1] * pixel_um
        for by, bx in self._blocks(y0, x0, y1, x1, 40.0):
            for y, x, radius, aspect, angle in self._specks(by, bx):
                canvas.ellipse(y - y0, x - x0, radius, _DUST_OD, aspect=aspect, angle=angle)
        for y, x, radius in self._bubbles():
            canvas.ring(y - y0, x - x0, radius, 1.5, _BUBBLE_RIM_OD)
        return np.exp(-canvas.od[..., 0])

    def truth(self, samples: int = 48) -> TileTruth:
        """What is in each tile (see `TileTruth`), the tissue share sampled on a
        `samples` x `samples` grid of the tile."""
        rows, cols = self.grid.shape
        share = np.zeros((rows, cols))
        dust = np.full((rows, cols), np.nan)
        fold = np.full((rows, cols), np.nan)
        height, width = self.tile_um
        bands = self._shape_fields[3]
        for row in range(rows):
            for col in range(cols):
                y0, x0 = self._tile_origin_um(row, col)
                yy = (y0 + (np.arange(samples) + 0.5) * height / samples)[:, None]
                xx = (x0 + (np.arange(samples) + 0.5) * width / samples)[None, :]
                share[row, col] = float(self.tissue_mask(yy, xx).mean())
                for band in bands:
                    inside = band.distance_um(yy, xx) < band.half_width_um
                    if np.any(inside & (self.tissue_mask(yy, xx) > 0.5)):
                        fold[row, col] = band.dz_um
                        break
                if self._dust_in(y0, x0, y0 + height, x0 + width):
                    dust[row, col] = self.dust_above_um[row, col]
        return TileTruth(share, share < EMPTY_BELOW, dust, fold)

    def _dust_in(self, y0: float, x0: float, y1: float, x1: float) -> bool:
        """Whether a speck or a bubble's rim lies in the window (y0, x0)-(y1, x1), um."""
        for by, bx in self._blocks(y0, x0, y1, x1, 0.0):
            for y, x, *_ in self._specks(by, bx):
                if y0 <= y <= y1 and x0 <= x <= x1:
                    return True
        for y, x, radius in self._bubbles():
            nearest_um = math.hypot(y - min(max(y, y0), y1), x - min(max(x, x0), x1))
            farthest_um = math.hypot(max(abs(y - y0), abs(y - y1)), max(abs(x - x0), abs(x - x1)))
            if nearest_um <= radius <= farthest_um:  # the rim crosses the window
                return True
        return False


def _erfinv(p: float) -> float:
    """The inverse error function, by bisection (a threshold, once per slide)."""
    low, high = -6.0, 6.0
    for _ in range(60):
        mid = (low + high) / 2
        if math.erf(mid) < p:
            low = mid
        else:
            high = mid
    return (low + high) / 2


def tissue_slides(
    seed: int,
    n_slides: int,
    surface: SurfaceSpec,
    shape: tuple[int, int],
    pixel_um: float,
    spec: TissueSlideSpec | None = None,
) -> list[TissueSlide]:
    """`n_slides` virtual slides named slide-0, slide-1, ...: tiles of `shape` (height,
    width) pixels of `pixel_um` overlapping by `spec.overlap` (rounded to whole pixels, so
    that neighbours share their pixels exactly); the section's heights from the map family
    `surface` (per tile) plus the slide's tilt; the coverslip above, wedged."""
    spec = spec or TissueSlideSpec()
    tile_um = (shape[0] * pixel_um, shape[1] * pixel_um)
    pitch_um = round(shape[1] * (1.0 - spec.overlap)) * pixel_um
    grid = ScanGrid(surface.rows, surface.cols, pitch_um)
    slides = []
    for index in range(n_slides):
        rng = np.random.default_rng([seed, index, 30])
        y_mm = np.arange(surface.rows)[:, None] * pitch_um / 1000.0
        x_mm = np.arange(surface.cols)[None, :] * pitch_um / 1000.0
        tilt = rng.normal(0.0, spec.tilt_um_per_mm, 2)
        focus_um = generate_surface(surface, rng) + tilt[0] * y_mm + tilt[1] * x_mm
        wedge = rng.normal(0.0, spec.wedge_um_per_mm, 2)
        low, high = spec.coverslip_above_um
        above_um = rng.uniform(low, high) + wedge[0] * y_mm + wedge[1] * x_mm
        above_um = np.clip(above_um - focus_um + focus_um.mean(), low, high)
        slides.append(
            TissueSlide(
                f"slide-{index}",
                focus_um,
                grid,
                (seed, index),
                tile_um=tile_um,
                dust_above_um=above_um,
                spec=spec,
            )
        )
    return slides
