"""Phase specimens: unstained, nearly transparent objects that delay light more than their
surroundings, as a partially coherent brightfield microscope images them (`optics.AbbeImager`).

A tile is a `PhaseObject`: its optical path difference to the medium around it,
OPD(x, y) = sum over materials of (n - n_medium) x thickness (um), and a weak optical
density. Its complex transmittance at wavelength lambda is

    t(x, y) = exp(-density / 2) exp(i phi),  phi = 2 pi OPD / lambda  (radians),

so a feature of thickness h and index contrast dn shifts the phase by 2 pi dn h / lambda
(dispersion neglected: one OPD for any wavelength of the green filter).

- `cell_culture`: flat adherent cells in medium (n 1.335), 10-40 um, cytoplasm
  (n 1.36-1.38) 1-2 um thick with a few thin lamellipodia at its rim and a granular
  texture, a domed nucleus raising the cell to 2.5-4 um, and 1-3 nucleoli of higher
  index. Phase: about 0.3-1 rad over cytoplasm, 1.5-2.5 rad over nucleoli.
- `red_cells`: an unstained blood smear's red cells in plasma (n 1.345): biconcave
  discs 7-8 um across (the Evans-Fung shape: 2.2-2.6 um at the rim, 0.7-0.8 um in the
  centre) of haemoglobin solution (n 1.39-1.41), a monolayer that does not overlap,
  and platelets. Phase: about 1.5-2 rad at the rim, 0.5 rad in the centre.

Both absorb little (density of 0.01-0.02 per um of cell at 0.53 um). Everything is drawn
from the given seed: a tile looks the same every time it is imaged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from focustrack_instrument_sim.specimen import _Canvas, _granules, _scatter

#: Channels of the canvas a phase specimen is drawn on.
_OPD, _DENSITY = 0, 1
#: The true phase below which a pixel is glass (the medium around the cells has none).
GLASS_PHASE_RAD = 1e-6


@dataclass(frozen=True)
class PhaseObject:
    """A thin phase specimen over one tile.

    opd_um: float32 (height, width), optical path difference to the surrounding medium, um.
    density: float32 (height, width), optical density (intensity transmission exp(-density)).
    """

    opd_um: np.ndarray
    density: np.ndarray

    def phase_rad(self, wavelength_um: float) -> np.ndarray:
        """phi = 2 pi OPD / lambda, float32 (height, width), radians (not wrapped)."""
        return (self.opd_um * np.float32(2.0 * np.pi / wavelength_um)).astype(np.float32)

    def transmittance(self, wavelength_um: float) -> np.ndarray:
        """t = exp(-density / 2) exp(i phi), complex64 (height, width)."""
        amplitude = np.exp(-0.5 * self.density)
        return (amplitude * np.exp(1j * self.phase_rad(wavelength_um))).astype(np.complex64)


@dataclass(frozen=True)
class PhaseSpecimenSpec:
    """Composition of the phase specimens. Lengths in um; densities per 1000 um^2 of a
    full field; refractive indices at the illumination's wavelength."""

    # cells in culture
    n_medium: float = 1.335  # culture medium
    n_cytoplasm: tuple[float, float] = (1.36, 1.38)  # drawn per cell
    n_nucleus_excess: float = 0.005  # nucleus over its cell's cytoplasm
    n_nucleolus_excess: float = 0.02  # nucleoli over their nucleus
    cell_density: float = 1.0  # about three cells over a 55-um field
    cell_diameter_um: tuple[float, float] = (10.0, 40.0)
    cytoplasm_um: tuple[float, float] = (1.0, 2.0)  # thickness at the cell's centre
    cell_um: tuple[float, float] = (2.5, 4.0)  # thickness over the nucleus
    cell_density_per_um: float = 0.01  # optical density per um of cell
    # an unstained blood smear
    n_plasma: float = 1.345
    n_haemoglobin: tuple[float, float] = (1.39, 1.41)  # drawn per red cell
    n_platelet: float = 1.375
    red_cell_density: float = 13.0  # a monolayer covering about 60% of the glass
    red_cell_diameter_um: float = 7.5
    platelet_density: float = 0.8
    red_cell_density_per_um: float = 0.02  # optical density per um of red cell
    empty_fraction: float = 0.05  # smear fields with no cells at all
    sparse_fraction: float = 0.15  # smear fields with 10-30% of the usual cells
    edge_um: float = 0.2  # width of the soft edge of every object


def _dome(rho: np.ndarray) -> np.ndarray:
    """Relative thickness of a flat cell: 35% at its rim, rising smoothly to 1 at its centre."""
    return 0.35 + 0.65 * (1.0 - rho * rho)


def _cap(rho: np.ndarray) -> np.ndarray:
    """Relative thickness of a spherical cap (a nucleus, a nucleolus): sqrt(1 - rho^2)."""
    return np.sqrt(np.maximum(1.0 - rho * rho, 0.0))


def evans_fung_um(rho: np.ndarray) -> np.ndarray:
    """Thickness (um) of a red cell at relative radius rho (Evans and Fung 1972, a cell
    of 7.8 um): sqrt(1 - rho^2) (0.81 + 7.83 rho^2 - 4.39 rho^4), 0.81 um in the centre,
    2.57 um at most (rho ~ 0.7)."""
    r2 = rho * rho
    return np.sqrt(np.maximum(1.0 - r2, 0.0)) * (0.81 + 7.83 * r2 - 4.39 * r2 * r2)


def _material(dn: float, density_per_um: float) -> np.ndarray:
    """A canvas value per um of thickness: (OPD, density)."""
    return np.array([dn, density_per_um], dtype=np.float32)


def _phase_object(canvas: _Canvas) -> PhaseObject:
    return PhaseObject(
        np.ascontiguousarray(canvas.od[..., _OPD]), np.ascontiguousarray(canvas.od[..., _DENSITY])
    )


def cell_culture(
    spec: PhaseSpecimenSpec, seed: np.random.SeedSequence, shape: tuple[int, int], pixel_um: float
) -> PhaseObject:
    """Unstained adherent cells in culture over one field (height, width) of `pixel_um`."""
    rng = np.random.default_rng(seed)
    canvas = _Canvas(shape, pixel_um, spec.edge_um, channels=2)
    area_k_um2 = canvas.size_um[0] * canvas.size_um[1] / 1000.0
    # cytoplasm granules: about +-10% of its thickness, smooth over 0.25 um
    texture = 1.0 + 0.15 * (_granules(rng, shape, pixel_um) - 1.0)
    n_cells = rng.poisson(spec.cell_density * area_k_um2)
    low_um, high_um = spec.cell_diameter_um
    for y, x in _scatter(rng, n_cells, canvas.size_um, 1.5 * low_um, []):
        radius = rng.uniform(low_um, high_um) / 2.0
        aspect, angle = rng.uniform(1.0, 1.8), rng.uniform(0, np.pi)
        major = radius * np.sqrt(aspect)  # the ellipse's area stays pi radius^2
        minor = major / aspect
        n_cell = rng.uniform(*spec.n_cytoplasm)
        cytoplasm = _material(n_cell - spec.n_medium, spec.cell_density_per_um)
        cytoplasm_um = rng.uniform(*spec.cytoplasm_um)
        canvas.ellipse(y, x, minor, cytoplasm * cytoplasm_um, aspect=aspect, angle=angle,
                       profile=_dome, texture=texture)  # fmt: skip
        for side in rng.uniform(0, 2 * np.pi, size=rng.integers(1, 4)):  # lamellipodia
            reach = 0.8 * minor
            canvas.ellipse(y + reach * np.sin(side), x + reach * np.cos(side),
                           rng.uniform(0.3, 0.5) * minor, cytoplasm * rng.uniform(0.3, 0.6),
                           aspect=rng.uniform(1.0, 2.0), angle=side + np.pi / 2,
                           profile=_cap)  # fmt: skip
        nucleus_radius = min(rng.uniform(0.35, 0.5) * minor, 7.0)
        ny = y + rng.uniform(-0.2, 0.2) * minor
        nx = x + rng.uniform(-0.2, 0.2) * minor
        raise_um = rng.uniform(*spec.cell_um) - cytoplasm_um
        nucleus = _material(n_cell + spec.n_nucleus_excess - spec.n_medium,
                            spec.cell_density_per_um)  # fmt: skip
        canvas.ellipse(ny, nx, nucleus_radius, nucleus * raise_um, aspect=rng.uniform(1.0, 1.3),
                       angle=rng.uniform(0, np.pi), profile=_cap)  # fmt: skip
        # the nucleus, thicker than the cytoplasm it replaces, also has a higher index there
        excess = _material(spec.n_nucleus_excess, 0.0) * cytoplasm_um
        canvas.ellipse(ny, nx, nucleus_radius, excess)
        for _ in range(rng.integers(1, 4)):
            angle_n, offset = rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.5 * nucleus_radius)
            canvas.ellipse(ny + offset * np.sin(angle_n), nx + offset * np.cos(angle_n),
                           rng.uniform(0.5, 1.0), _material(spec.n_nucleolus_excess, 0.0),
                           profile=_cap)  # fmt: skip
    return _phase_object(canvas)


def red_cells(
    spec: PhaseSpecimenSpec, seed: np.random.SeedSequence, shape: tuple[int, int], pixel_um: float
) -> PhaseObject:
    """An unstained blood smear's red cells and platelets in plasma over one field."""
    rng = np.random.default_rng(seed)
    canvas = _Canvas(shape, pixel_um, spec.edge_um, channels=2)
    area_k_um2 = canvas.size_um[0] * canvas.size_um[1] / 1000.0
    kind = rng.uniform()
    if kind < spec.empty_fraction:
        return _phase_object(canvas)
    fullness = rng.uniform(0.1, 0.3) if kind < spec.empty_fraction + spec.sparse_fraction else 1.0
    fullness *= rng.uniform(0.75, 1.1)
    red_radius = spec.red_cell_diameter_um / 2.0
    n_red = rng.poisson(spec.red_cell_density * area_k_um2 * fullness)
    for y, x in _scatter(rng, n_red, canvas.size_um, 2.0 * red_radius, []):  # a monolayer
        radius = red_radius * rng.normal(1.0, 0.06)
        scale = rng.uniform(0.85, 1.0)  # thickness: 2.2-2.6 um at the rim
        haemoglobin = _material(rng.uniform(*spec.n_haemoglobin) - spec.n_plasma,
                                spec.red_cell_density_per_um)  # fmt: skip
        canvas.ellipse(y, x, radius, haemoglobin, aspect=rng.uniform(1.0, 1.12),
                       angle=rng.uniform(0, np.pi),
                       profile=lambda rho, scale=scale: scale * evans_fung_um(rho))  # fmt: skip
    n_platelets = rng.poisson(spec.platelet_density * area_k_um2 * fullness)
    platelet = _material(spec.n_platelet - spec.n_plasma, spec.red_cell_density_per_um)
    for y, x in rng.uniform((0.0, 0.0), canvas.size_um, size=(n_platelets, 2)):
        canvas.ellipse(y, x, rng.uniform(0.8, 1.5), platelet, aspect=rng.uniform(1.0, 1.4),
                       angle=rng.uniform(0, np.pi), profile=_cap)  # fmt: skip
    return _phase_object(canvas)
