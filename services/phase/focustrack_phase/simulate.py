"""Synthetic through-focus stacks: the paper's Data Set 1 with a weak object of our own.

Data Set 1 (section 5): 100 images of 100x100 pixels of 1 um, 532 nm, planes in 0.5 um
steps over 50 um from focus (z = 0.5, 1.0, ..., 50 um), Poisson noise with gamma = 0.998:
by eq. 5 the counts are Poisson(gamma |a|^2) with the field normalised to mean |a|^2 = 1
(which propagation keeps), so a pixel detects gamma photons on average.

The paper does not give its object. Ours is a weak blood smear: unstained red cells as
phase objects (Evans-Fung biconcave discs, 7.0-8.2 um across, 0.8 um thick in the middle
and 2.6 um at the rim, placed at random without overlapping, 60 of them in 100x100 um),
their phase scaled to at most `WEAK_PEAK_PHASE_RAD` = 0.5 rad (a real red cell in plasma
reaches about 1.5-2 rad at 532 nm: the paper's theory is for weak objects) and a weak
absorption (3% of the amplitude at the rim). Discs of 7-8 um put the phase where these
planes see it (periods of 4-20 um; periods over 20 um barely change within 50 um). The
field wraps around the edges, as the periodic angular spectrum the filter assumes does
(the paper's synthetic data are made the same way).

`through_focus_stack` images it with coherent light; `partially_coherent_stack` with a
disk source of a given condenser NA (Abbe's method: the intensities of tilted plane waves
from points of the source, added), for the filter's partial-coherence model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from focustrack_phase.propagation import propagate

DATA_SET_1_PLANES = 100
DATA_SET_1_SIZE_PX = 100
DATA_SET_1_PIXEL_UM = 1.0
DATA_SET_1_WAVELENGTH_UM = 0.532
DATA_SET_1_STEP_UM = 0.5
DATA_SET_1_GAMMA = 0.998


@dataclass(frozen=True)
class SyntheticStack:
    """A simulated stack and its truth.

    field: complex128 (height, width) at z = 0, mean |field|^2 = 1 (dimensionless).
    stack_counts: float64 (frames, height, width) Poisson photon counts.
    z_um: float64 (frames,) each frame's height above focus (um).
    """

    field: np.ndarray
    stack_counts: np.ndarray
    z_um: np.ndarray
    wavelength_um: float
    pixel_um: float
    gamma_photons: float


WEAK_PEAK_PHASE_RAD = 0.5
RED_CELLS = 60


def red_cell_thickness_um(rho: np.ndarray) -> np.ndarray:
    """Evans-Fung thickness (um) of a red cell at radius rho (0..1 of the cell's radius)."""
    rho2 = np.clip(rho * rho, 0.0, 1.0)
    return np.sqrt(1.0 - rho2) * (0.81 + 7.83 * rho2 - 4.39 * rho2 * rho2)


def weak_object(
    size_px: int, seed: int, peak_phase_rad: float = WEAK_PEAK_PHASE_RAD, smooth_um: float = 0.0
) -> np.ndarray:
    """A weak red-cell smear (complex (size, size), mean |a|^2 = 1): see the module's text.

    Pixels are taken as 1 um (Data Set 1's); the cells keep their size in pixels otherwise.
    smooth_um > 0 blurs the cells' thickness by a Gaussian of that sigma (periodic) before
    scaling to `peak_phase_rad`: a smooth, low-bandwidth object without sharp rims.
    """
    if size_px < 16:
        raise ValueError(f"size_px must be >= 16, got {size_px}")
    rng = np.random.default_rng([seed, 29])
    thickness_um = np.zeros((size_px, size_px))
    centres = np.empty((0, 2))
    diameters = np.empty(0)
    count = round(RED_CELLS * size_px * size_px / 100.0**2)
    for _ in range(50 * count):
        if len(diameters) == count:
            break
        centre, diameter = rng.uniform(0.0, size_px, size=2), rng.uniform(7.0, 8.2)
        if np.any(_wrapped_distances(centres, centre, size_px) < 0.5 * (diameters + diameter)):
            continue
        centres = np.vstack([centres, centre])
        diameters = np.append(diameters, diameter)
        # Only the pixels within the cell's radius change: a patch around it (wrapped), so
        # a smear of thousands of cells costs each cell its own few dozen pixels.
        rows, cols = (
            np.arange(int(c - 0.5 * diameter) - 1, int(c + 0.5 * diameter) + 2) % size_px
            for c in centre
        )
        dy = (rows[:, None] - centre[0] + size_px / 2) % size_px - size_px / 2
        dx = (cols[None, :] - centre[1] + size_px / 2) % size_px - size_px / 2
        rho = np.sqrt(dx * dx + dy * dy) / (0.5 * diameter)
        thickness_um[np.ix_(rows, cols)] += np.where(rho < 1.0, red_cell_thickness_um(rho), 0.0)
    if smooth_um > 0:
        thickness_um = ndimage.gaussian_filter(thickness_um, smooth_um, mode="wrap")
    relative = thickness_um / max(float(thickness_um.max()), 1e-12)
    field = (1.0 - 0.03 * relative) * np.exp(1j * peak_phase_rad * relative)
    return field / np.sqrt(np.mean(np.abs(field) ** 2))


def _wrapped_distances(centres: np.ndarray, centre: np.ndarray, period: float) -> np.ndarray:
    """Distances (n,) from `centre` (2,) to each of `centres` (n, 2) on a torus of `period`."""
    delta = (centres - centre + period / 2) % period - period / 2
    return np.hypot(delta[:, 0], delta[:, 1])


def through_focus_stack(
    field: np.ndarray,
    z_um: np.ndarray,
    wavelength_um: float,
    pixel_um: float,
    gamma_photons: float,
    seed: int,
) -> np.ndarray:
    """Poisson photon counts (frames, height, width) of `field` propagated to each z (eq. 2)."""
    rng = np.random.default_rng([seed, 2])
    stack = np.empty((len(z_um), *field.shape))
    for k, z in enumerate(z_um):
        intensity = np.abs(propagate(field, float(z), wavelength_um, pixel_um)) ** 2
        stack[k] = rng.poisson(gamma_photons * intensity)
    return stack


def source_points_per_um(
    condenser_na: float, wavelength_um: float, shape: tuple[int, int], pixel_um: float
) -> np.ndarray:
    """Spatial frequencies (1/um, (n, 2) as (fy, fx)) of the source points of a disk source.

    Every frequency of the image's FFT grid within condenser_na / wavelength, so each
    tilted plane wave is periodic on the grid (the field wraps around, as propagation
    does); the on-axis point alone for condenser_na = 0 (coherent light).
    """
    fy = np.fft.fftfreq(shape[0], d=pixel_um)
    fx = np.fft.fftfreq(shape[1], d=pixel_um)
    grid = np.stack(np.meshgrid(fy, fx, indexing="ij"), axis=-1).reshape(-1, 2)
    radius = condenser_na / wavelength_um
    return grid[np.hypot(grid[:, 0], grid[:, 1]) <= radius + 1e-12]


def partially_coherent_stack(
    field: np.ndarray,
    z_um: np.ndarray,
    wavelength_um: float,
    pixel_um: float,
    gamma_photons: float,
    condenser_na: float,
    seed: int,
) -> np.ndarray:
    """Poisson counts (frames, height, width) of `field` lit by a disk source (Abbe).

    Each source point s lights the object with the plane wave exp(2 pi i s.x); the mean
    of the propagated intensities over the points is the partially coherent image.
    """
    points = source_points_per_um(condenser_na, wavelength_um, field.shape, pixel_um)
    yy, xx = np.mgrid[0 : field.shape[0], 0 : field.shape[1]] * pixel_um
    rng = np.random.default_rng([seed, 2])
    stack = np.empty((len(z_um), *field.shape))
    for k, z in enumerate(z_um):
        intensity = np.zeros(field.shape)
        for fy, fx in points:
            tilted = field * np.exp(2j * np.pi * (fy * yy + fx * xx))
            intensity += np.abs(propagate(tilted, float(z), wavelength_um, pixel_um)) ** 2
        stack[k] = rng.poisson(gamma_photons * intensity / len(points))
    return stack


def data_set_1(
    seed: int = 1,
    gamma_photons: float = DATA_SET_1_GAMMA,
    planes: int = DATA_SET_1_PLANES,
    size_px: int = DATA_SET_1_SIZE_PX,
    peak_phase_rad: float = WEAK_PEAK_PHASE_RAD,
    smooth_um: float = 0.0,
) -> SyntheticStack:
    """The paper's Data Set 1; fewer `planes` spread over the same 50 um (every k-th plane).

    planes must divide 100 evenly for the planes to be a subset of the full stack. The
    object is `weak_object(size_px, seed, peak_phase_rad, smooth_um)`.
    """
    if not 1 <= planes <= DATA_SET_1_PLANES:
        raise ValueError(f"planes must be in 1..{DATA_SET_1_PLANES}, got {planes}")
    span_um = DATA_SET_1_PLANES * DATA_SET_1_STEP_UM
    z_um = np.arange(1, planes + 1) * (span_um / planes)
    field = weak_object(size_px, seed, peak_phase_rad, smooth_um)
    stack = through_focus_stack(
        field, z_um, DATA_SET_1_WAVELENGTH_UM, DATA_SET_1_PIXEL_UM, gamma_photons, seed
    )
    return SyntheticStack(
        field, stack, z_um, DATA_SET_1_WAVELENGTH_UM, DATA_SET_1_PIXEL_UM, gamma_photons
    )
