"""The specimen: a thin Giemsa-stained blood smear as a 60x brightfield objective sees it.

A tile is rendered as its RGB transmission (Beer-Lambert: exp(-optical density)),
shape (height, width, 3), float32 in (0, 1]. Optical densities per channel are
those of the stains (illustrative, tuned by eye to the usual look): haemoglobin
absorbs green and blue (red cells look salmon), Giemsa-stained chromatin absorbs
green and red (purple nuclei, platelets and parasite chromatin), parasite
cytoplasm absorbs red (blue rings).

- Red cells: biconcave discs, 7-8 um, thin in the middle (the central pallor),
  slightly elliptical, a monolayer that barely overlaps.
- White cells: larger, with a dark lobed (neutrophil) or round (lymphocyte) nucleus.
- Platelets: small purple granular blobs.
- Parasites: ring forms with a chromatin dot inside some red cells.
- Fields vary: most are full, some sparse, a few empty (nothing but plasma).
- Optional dust: grey specks on another plane (`dust_layer`), to tempt a focus
  algorithm towards a second peak.

Everything is drawn from the given seed: a tile looks the same every time it is imaged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from focustrack_instrument_sim.simulator_options import default

# Optical density (R, G, B) of each material at full thickness.
_PLASMA_OD = np.array([0.015, 0.025, 0.015], dtype=np.float32)
_HAEMOGLOBIN_OD = np.array([0.08, 0.55, 0.35], dtype=np.float32)
_CHROMATIN_OD = np.array([0.85, 1.25, 0.45], dtype=np.float32)
_WBC_CYTOPLASM_OD = np.array([0.12, 0.14, 0.05], dtype=np.float32)
_PLATELET_OD = np.array([0.35, 0.6, 0.2], dtype=np.float32)
_PARASITE_OD = np.array([0.5, 0.45, 0.12], dtype=np.float32)
_DUST_OD = 0.7


@dataclass(frozen=True)
class SpecimenSpec:
    """Composition of the smear. Lengths in um, densities per 1000 um^2 of a full field."""

    red_cell_density: float = 13.0  # a monolayer covering about 60% of the glass
    red_cell_diameter_um: float = 7.5
    white_cell_density: float = 0.04
    platelet_density: float = 0.8
    parasitaemia: float = 0.04  # fraction of red cells carrying a ring form
    empty_fraction: float = 0.05  # fields with no cells at all
    sparse_fraction: float = 0.15  # fields with 10-30% of the usual cells
    edge_um: float = 0.2  # width of the soft edge of every object
    dust_density: float = default("dust_density")  # grey specks per 1000 um^2 (0: no dust layer)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class _Canvas:
    """An image (height, width, channels) that objects are stamped into, in um: optical
    densities of the R, G, B channels here, optical path and density for phase specimens
    (`phase_specimen`)."""

    def __init__(
        self, shape: tuple[int, int], pixel_um: float, edge_um: float, channels: int = 3
    ) -> None:
        self.od = np.zeros((*shape, channels), dtype=np.float32)
        self.pixel_um = pixel_um
        self.edge_um = edge_um

    @property
    def size_um(self) -> tuple[float, float]:
        height, width = self.od.shape[:2]
        return height * self.pixel_um, width * self.pixel_um

    def _window(self, y_um: float, x_um: float, reach_um: float):
        """Pixel slices around (y, x) and the local coordinates (um) of their centres."""
        height, width = self.od.shape[:2]
        p = self.pixel_um
        y0, y1 = max(int((y_um - reach_um) / p), 0), min(int((y_um + reach_um) / p) + 2, height)
        x0, x1 = max(int((x_um - reach_um) / p), 0), min(int((x_um + reach_um) / p) + 2, width)
        if y0 >= y1 or x0 >= x1:
            return None
        yy = ((np.arange(y0, y1) + 0.5) * p - y_um)[:, None]
        xx = ((np.arange(x0, x1) + 0.5) * p - x_um)[None, :]
        return (slice(y0, y1), slice(x0, x1)), yy, xx

    def ellipse(
        self,
        y_um: float,
        x_um: float,
        radius_um: float,
        od: np.ndarray,
        *,
        aspect: float = 1.0,
        angle: float = 0.0,
        profile=None,
        texture: np.ndarray | None = None,
    ) -> None:
        """Add an ellipse of `od` (one value per channel) x thickness `profile(rho)` (rho: 0
        at the centre, 1 at the rim)."""
        window = self._window(y_um, x_um, radius_um * max(aspect, 1.0) + self.edge_um)
        if window is None:
            return
        (rows, cols), yy, xx = window
        c, s = np.cos(angle), np.sin(angle)
        u = (xx * c + yy * s) / aspect
        v = -xx * s + yy * c
        distance_um = np.sqrt(u * u + v * v)
        weight = _smoothstep((radius_um - distance_um) / self.edge_um + 0.5)
        if profile is not None:
            weight = weight * profile(np.minimum(distance_um / radius_um, 1.0))
        if texture is not None:
            weight = weight * texture[rows, cols]
        self.od[rows, cols] += weight[..., None].astype(np.float32) * od

    def ring(self, y_um: float, x_um: float, radius_um: float, width_um: float, od: np.ndarray):
        """Add a thin ring (a parasite's cytoplasm)."""
        window = self._window(y_um, x_um, radius_um + width_um + self.edge_um)
        if window is None:
            return
        (rows, cols), yy, xx = window
        off_ring_um = np.abs(np.sqrt(yy * yy + xx * xx) - radius_um)
        weight = _smoothstep((width_um / 2.0 - off_ring_um) / self.edge_um + 0.5)
        self.od[rows, cols] += weight[..., None].astype(np.float32) * od


def _red_cell_thickness(rho: np.ndarray) -> np.ndarray:
    """Relative thickness of a biconcave disc: 35% in the centre (the pallor), full at the rim."""
    return 0.35 + 0.65 * np.sin(np.pi / 2.0 * np.minimum(rho / 0.75, 1.0)) ** 2


def _scatter(
    rng: np.random.Generator, n: int, size_um: tuple[float, float], spacing_um: float,
    taken: list[tuple[float, float, float]],
) -> list[tuple[float, float]]:  # fmt: skip
    """Up to `n` points at least `spacing_um` from each other and clear of `taken` (y, x, r)."""
    placed: list[tuple[float, float]] = []
    points = np.empty((0, 2))
    blockers = np.array([(y, x) for y, x, _ in taken]).reshape(-1, 2)
    reach = np.array([r for *_, r in taken])
    for _ in range(4 * n):
        if len(placed) == n:
            break
        candidate = rng.uniform((0.0, 0.0), size_um)
        if len(points) and np.min(np.hypot(*(points - candidate).T)) < spacing_um:
            continue
        if len(blockers) and np.any(np.hypot(*(blockers - candidate).T) < reach):
            continue
        placed.append((float(candidate[0]), float(candidate[1])))
        points = np.vstack([points, candidate])
    return placed


def _granules(rng: np.random.Generator, shape: tuple[int, int], pixel_um: float) -> np.ndarray:
    """A smooth positive texture around 1 (chromatin and platelet granularity)."""
    # Imported here, when the simulator first renders: the service answers before then.
    from scipy import ndimage

    noise = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), 0.25 / pixel_um)
    return np.clip(1.0 + 0.6 * noise / max(float(noise.std()), 1e-6), 0.2, None)


def blood_smear(
    spec: SpecimenSpec, seed: np.random.SeedSequence, shape: tuple[int, int], pixel_um: float
) -> np.ndarray:
    """Transmission (height, width, 3), float32 in (0, 1], of one field of the smear."""
    rng = np.random.default_rng(seed)
    canvas = _Canvas(shape, pixel_um, spec.edge_um)
    canvas.od += _PLASMA_OD
    area_k_um2 = canvas.size_um[0] * canvas.size_um[1] / 1000.0
    kind = rng.uniform()
    if kind < spec.empty_fraction:
        return np.exp(-canvas.od)
    fullness = rng.uniform(0.1, 0.3) if kind < spec.empty_fraction + spec.sparse_fraction else 1.0
    fullness *= rng.uniform(0.75, 1.1)
    texture = _granules(rng, shape, pixel_um)
    taken: list[tuple[float, float, float]] = []

    for y, x in _scatter(rng, rng.poisson(spec.white_cell_density * area_k_um2 * fullness),
                         canvas.size_um, 15.0, []):  # fmt: skip
        radius = rng.uniform(5.0, 6.5)
        canvas.ellipse(y, x, radius, _WBC_CYTOPLASM_OD)
        if rng.uniform() < 0.6:  # neutrophil: 3-4 lobes
            for angle in rng.uniform(0, 2 * np.pi) + np.arange(rng.integers(3, 5)) * 1.7:
                canvas.ellipse(y + 2.2 * np.sin(angle), x + 2.2 * np.cos(angle),
                               rng.uniform(1.4, 1.9), _CHROMATIN_OD, texture=texture)  # fmt: skip
        else:  # lymphocyte: one large round nucleus
            canvas.ellipse(y, x, 0.8 * radius, _CHROMATIN_OD, texture=texture)
        taken.append((y, x, radius + 3.0))

    red_radius = spec.red_cell_diameter_um / 2.0
    n_red = rng.poisson(spec.red_cell_density * area_k_um2 * fullness)
    for y, x in _scatter(rng, n_red, canvas.size_um, 1.75 * red_radius, taken):
        radius = red_radius * rng.normal(1.0, 0.06)
        canvas.ellipse(y, x, radius, _HAEMOGLOBIN_OD, aspect=rng.uniform(1.0, 1.12),
                       angle=rng.uniform(0, np.pi), profile=_red_cell_thickness)  # fmt: skip
        if rng.uniform() < spec.parasitaemia:
            angle, offset = rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.4 * radius)
            py, px = y + offset * np.sin(angle), x + offset * np.cos(angle)
            ring_radius = rng.uniform(0.7, 1.1)
            canvas.ring(py, px, ring_radius, 0.3, _PARASITE_OD)
            dot = rng.uniform(0, 2 * np.pi)
            canvas.ellipse(py + ring_radius * np.sin(dot), px + ring_radius * np.cos(dot),
                           0.35, _CHROMATIN_OD)  # fmt: skip

    n_platelets = rng.poisson(spec.platelet_density * area_k_um2 * fullness)
    for y, x in rng.uniform((0.0, 0.0), canvas.size_um, size=(n_platelets, 2)):
        canvas.ellipse(y, x, rng.uniform(0.8, 1.5), _PLATELET_OD, aspect=rng.uniform(1.0, 1.4),
                       angle=rng.uniform(0, np.pi), texture=texture)  # fmt: skip
    return np.exp(-canvas.od)


def dust_layer(
    spec: SpecimenSpec, seed: np.random.SeedSequence, shape: tuple[int, int], pixel_um: float
) -> np.ndarray:
    """Grey transmission (height, width), float32, of the dust on another plane (1 = clean)."""
    rng = np.random.default_rng(seed)
    canvas = _Canvas(shape, pixel_um, 0.5)
    n_specks = rng.poisson(spec.dust_density * canvas.size_um[0] * canvas.size_um[1] / 1000.0)
    grey = np.full(3, _DUST_OD, dtype=np.float32)
    for y, x in rng.uniform((0.0, 0.0), canvas.size_um, size=(n_specks, 2)):
        canvas.ellipse(y, x, rng.uniform(1.0, 4.0), grey, aspect=rng.uniform(1.0, 2.5),
                       angle=rng.uniform(0, np.pi))  # fmt: skip
    return np.exp(-canvas.od[..., 0])
