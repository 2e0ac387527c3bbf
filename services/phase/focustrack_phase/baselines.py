"""Two linear baselines for the sparse ACEKF, on the same stacks and in the same units.

Both linearise the weak object a = 1 + alpha + i phi (alpha, phi real and small): with
the Fresnel transfer function of eq. 3, the intensity relative to the mean at height z is,
per spatial frequency f (chi = pi lambda z |f|^2),

    I_hat(f, z) = delta(f) + 2 cos(chi) A(f) + 2 sin(chi) Phi(f)     (weak-object transfer)

with A, Phi the unitary FFTs of alpha and phi.

- `tie_tikhonov`: transport of intensity, dI/dz at focus = 2 pi lambda |f|^2 Phi, with
  dI/dz the least-squares slope of the intensity over the planes within `max_dz_um` of
  focus (at least the two nearest; a line with an intercept, so one side of focus
  serves), inverted with Tikhonov regularisation `alpha`; the amplitude is the root of
  the window's mean intensity. More planes average the noise down, farther ones bend the
  line: the window is the classic trade-off.
- `weak_object_least_squares`: every plane's transfer functions, solved per frequency for
  (A, Phi) by least squares with Tikhonov regularisation `alpha` (normal equations of
  2x2, accumulated one frame at a time: five arrays of the image's size).
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from focustrack_phase.acekf import FieldEstimate, nearest_first, validate_stack
from focustrack_phase.propagation import frequency_sq_per_um2


def tie_tikhonov(
    stack_counts: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    photons_per_count: float = 1.0,
    alpha: float = 1e-2,
    max_dz_um: float = 0.0,
) -> FieldEstimate:
    """Phase (and the window's mean intensity) at z = 0 by a Tikhonov-regularised TIE.

    Arguments as `focustrack_phase.acekf.reconstruct`; `alpha` (1/um^2) is added to
    (2 pi lambda |f|^2)^2 in the inverse Laplacian; the slope is fitted over the planes
    within `max_dz_um` of focus, and at least the two nearest. Needs two planes at
    different z.
    """
    if not alpha > 0:
        raise ValueError(f"alpha must be > 0, got {alpha}")
    z, gamma = validate_stack(stack_counts, z_um, wavelength_um, pixel_um, photons_per_count)
    if len(np.unique(z)) < 2:
        raise ValueError("tie_tikhonov needs two planes at different heights")
    order = nearest_first(z)
    window = [int(k) for k in order if abs(z[k]) <= max_dz_um]
    for k in order:  # at least two planes at different heights
        if len(np.unique(z[window])) >= 2:
            break
        if int(k) not in window:
            window.append(int(k))
    dz = z[window] - z[window].mean()
    scale = photons_per_count / gamma
    frames = stack_counts[window] * scale
    mean_intensity = frames.mean(axis=0)
    didz = np.tensordot(dz, frames, axes=1) / float(dz @ dz)  # 1/um, relative intensity
    weight = 2.0 * np.pi * wavelength_um * frequency_sq_per_um2(didz.shape, pixel_um)
    phase_rad = fft.ifft2(
        fft.fft2(didz, norm="ortho") * weight / (weight * weight + alpha), norm="ortho"
    ).real
    amplitude = np.sqrt(np.maximum(mean_intensity, 0.0))
    return FieldEstimate(amplitude * np.exp(1j * phase_rad), gamma)


def weak_object_least_squares(
    stack_counts: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    photons_per_count: float = 1.0,
    alpha: float = 1.0,
) -> FieldEstimate:
    """Amplitude and phase at z = 0 from every plane's weak-object transfer functions.

    Arguments as `focustrack_phase.acekf.reconstruct`; `alpha` (dimensionless) is the
    Tikhonov weight on |A|^2 + |Phi|^2 against the sum of squared residuals of all planes.
    """
    if not alpha > 0:
        raise ValueError(f"alpha must be > 0, got {alpha}")
    z, gamma = validate_stack(stack_counts, z_um, wavelength_um, pixel_um, photons_per_count)
    freq_sq = frequency_sq_per_um2(stack_counts.shape[1:], pixel_um)
    scale = photons_per_count / gamma
    cc = np.zeros(freq_sq.shape)
    cs = np.zeros(freq_sq.shape)
    ss = np.zeros(freq_sq.shape)
    rhs_c = np.zeros(freq_sq.shape, dtype=np.complex128)
    rhs_s = np.zeros(freq_sq.shape, dtype=np.complex128)
    for k in range(len(z)):
        chi = (np.pi * wavelength_um * z[k]) * freq_sq
        c, s = 2.0 * np.cos(chi), 2.0 * np.sin(chi)
        measured = fft.fft2(stack_counts[k] * scale - 1.0, norm="ortho")
        cc += c * c
        cs += c * s
        ss += s * s
        rhs_c += c * measured
        rhs_s += s * measured
    cc += alpha
    ss += alpha
    det = cc * ss - cs * cs
    amp_hat = (ss * rhs_c - cs * rhs_s) / det
    phase_hat = (cc * rhs_s - cs * rhs_c) / det
    amplitude = 1.0 + fft.ifft2(amp_hat, norm="ortho").real
    phase_rad = fft.ifft2(phase_hat, norm="ortho").real
    return FieldEstimate(amplitude * np.exp(1j * phase_rad), gamma)
