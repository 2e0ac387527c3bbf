"""Synthetic through-focus stacks: the paper's Data Set 1 with a weak object of our own.

Data Set 1 (section 5): 100 images of 100x100 pixels of 1 um, 532 nm, planes in 0.5 um
steps over 50 um from focus (z = 0.5, 1.0, ..., 50 um), Poisson noise with gamma = 0.998:
by eq. 5 the counts are Poisson(gamma |a|^2) with the field normalised to mean |a|^2 = 1
(which propagation keeps), so a pixel detects gamma photons on average.

The paper does not give its object. Ours is smooth and weak: the amplitude is 1 minus a
sum of Gaussian absorbers (depths 0.05-0.15, widths 4-10 px) and the phase a sum of
Gaussian bumps (heights -0.3..0.6 rad, widths 3-12 px) with a range under 1 rad, the
whole placed at random by a seed. Propagation is the same periodic angular spectrum the
filter assumes (the paper's synthetic data are made the same way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def weak_object(size_px: int, seed: int) -> np.ndarray:
    """A smooth weak object (complex (size, size), mean |a|^2 = 1): see the module's text."""
    if size_px < 8:
        raise ValueError(f"size_px must be >= 8, got {size_px}")
    rng = np.random.default_rng([seed, 29])
    yy, xx = np.mgrid[0:size_px, 0:size_px].astype(np.float64)

    def bumps(
        count: int, heights: tuple[float, float], widths_px: tuple[float, float]
    ) -> np.ndarray:
        total = np.zeros((size_px, size_px))
        for _ in range(count):
            cy, cx = rng.uniform(0.15, 0.85, size=2) * size_px
            width = rng.uniform(*widths_px)
            total += rng.uniform(*heights) * np.exp(
                -((yy - cy) ** 2 + (xx - cx) ** 2) / (2.0 * width * width)
            )
        return total

    amplitude = 1.0 - bumps(6, (0.05, 0.15), (2.0, 6.0))
    phase_rad = bumps(12, (0.2, 0.6), (2.0, 6.0))
    phase_rad *= min(1.0, 0.9 / max(float(np.ptp(phase_rad)), 1e-12))  # range under 1 rad
    field = amplitude * np.exp(1j * phase_rad)
    return field / np.sqrt(np.mean(np.abs(field) ** 2))


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


def data_set_1(
    seed: int = 1,
    gamma_photons: float = DATA_SET_1_GAMMA,
    planes: int = DATA_SET_1_PLANES,
    size_px: int = DATA_SET_1_SIZE_PX,
) -> SyntheticStack:
    """The paper's Data Set 1; fewer `planes` spread over the same 50 um (every k-th plane).

    planes must divide 100 evenly for the planes to be a subset of the full stack.
    """
    if not 1 <= planes <= DATA_SET_1_PLANES:
        raise ValueError(f"planes must be in 1..{DATA_SET_1_PLANES}, got {planes}")
    span_um = DATA_SET_1_PLANES * DATA_SET_1_STEP_UM
    z_um = np.arange(1, planes + 1) * (span_um / planes)
    field = weak_object(size_px, seed)
    stack = through_focus_stack(
        field, z_um, DATA_SET_1_WAVELENGTH_UM, DATA_SET_1_PIXEL_UM, gamma_photons, seed
    )
    return SyntheticStack(
        field, stack, z_um, DATA_SET_1_WAVELENGTH_UM, DATA_SET_1_PIXEL_UM, gamma_photons
    )
