"""Paraxial free-space propagation by the angular spectrum (Fresnel transfer function).

Fields are complex arrays of shape (height, width) sampled at `pixel_um`; the FFT is the
unitary one (``norm="ortho"``, the paper's K with K K^H = U), so a field's energy is the
same in both domains and every plane.
"""

from __future__ import annotations

import numpy as np
from scipy import fft


def frequency_sq_per_um2(shape: tuple[int, int], pixel_um: float) -> np.ndarray:
    """fx^2 + fy^2 (1/um^2) of each FFT bin of an image of `shape` (height, width).

    The paper's (u/Lx)^2 + (v/Ly)^2 of eq. 3, with Lx = width * pixel_um. Symmetric in
    (u, v) -> (-u, -v) on the FFT grid, as Lemma 1 needs.
    """
    if len(shape) != 2 or min(shape) < 1:
        raise ValueError(f"shape must be (height, width) with both >= 1, got {shape}")
    if not pixel_um > 0:
        raise ValueError(f"pixel_um must be > 0, got {pixel_um}")
    fy = fft.fftfreq(shape[0], d=pixel_um)
    fx = fft.fftfreq(shape[1], d=pixel_um)
    return np.add.outer(fy * fy, fx * fx)


def fresnel_transfer(freq_sq_per_um2: np.ndarray, wavelength_um: float, dz_um: float) -> np.ndarray:
    """The diagonal of H (eq. 3) from one plane to another `dz_um` further (either sign).

    exp(-i pi lambda (fx^2 + fy^2) dz): modulus 1, so propagation is unitary and
    H(-dz) = H(dz)^* undoes H(dz). complex64 for float32 frequencies, complex128 otherwise.
    """
    if not wavelength_um > 0:
        raise ValueError(f"wavelength_um must be > 0, got {wavelength_um}")
    phase_rad = (-np.pi * wavelength_um * dz_um) * freq_sq_per_um2
    transfer = np.empty(phase_rad.shape, dtype=np.result_type(phase_rad, np.complex64))
    np.cos(phase_rad, out=transfer.real)  # cos + i sin: a third of exp's time on complex
    np.sin(phase_rad, out=transfer.imag)
    return transfer


def propagate(field: np.ndarray, dz_um: float, wavelength_um: float, pixel_um: float) -> np.ndarray:
    """The complex field (height, width) `dz_um` further along z (eq. 4: b_n = H b_{n-1})."""
    if field.ndim != 2:
        raise ValueError(f"field must be 2-D (height, width), got shape {field.shape}")
    transfer = fresnel_transfer(frequency_sq_per_um2(field.shape, pixel_um), wavelength_um, dz_um)
    return fft.ifft2(transfer * fft.fft2(field, norm="ortho"), norm="ortho")
