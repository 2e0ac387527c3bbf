"""Paraxial free-space propagation by the angular spectrum (Fresnel transfer function).

Fields are complex arrays of shape (height, width) sampled at `pixel_um`; the FFT is the
unitary one (``norm="ortho"``, the paper's K with K K^H = U), so a field's energy is the
same in both domains and every plane.
"""

from __future__ import annotations

import numpy as np
from scipy import fft, special


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


def coherence_envelope(
    freq_sq_per_um2: np.ndarray, z_um: float, condenser_na: float
) -> np.ndarray | None:
    """2 J1(v)/v, v = 2 pi |z| condenser_na |f|: a disk source's damping of the intensity's
    linear response at defocus z (float32, the shape of `freq_sq_per_um2`; None for
    coherent light, where it is 1)."""
    if condenser_na == 0:
        return None
    v = (2.0 * np.pi * abs(z_um) * condenser_na) * np.sqrt(freq_sq_per_um2)
    envelope = np.ones_like(v)
    nonzero = v > 1e-12
    envelope[nonzero] = 2.0 * special.j1(v[nonzero]) / v[nonzero]
    return envelope.astype(np.float32)


def phase_transfer_power(
    freq_sq_per_um2: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    condenser_na: float = 0.0,
) -> np.ndarray:
    """T(f): the mean over the planes of (2 sin(pi lambda z |f|^2) E_z(f))^2 (float64, the
    shape of `freq_sq_per_um2`), dimensionless.

    A weak phase at frequency f moves plane z's relative intensity by 2 sin(pi lambda z
    |f|^2) times the phase (the weak-object transfer), damped by the coherence envelope
    E_z; T is that response's power averaged over the stack, so gamma N_z T(f) is the
    information the stack carries on the phase at f (per unitary Fourier coefficient). It
    rises from 0 at f = 0 like f^4 and averages 2 once the planes' sines oscillate.
    """
    power = np.zeros(freq_sq_per_um2.shape)
    for z in z_um:
        response = 2.0 * np.sin((np.pi * wavelength_um * float(z)) * freq_sq_per_um2)
        envelope = coherence_envelope(freq_sq_per_um2, float(z), condenser_na)
        if envelope is not None:
            response *= envelope
        power += response * response
    return power / max(len(z_um), 1)


def propagate(field: np.ndarray, dz_um: float, wavelength_um: float, pixel_um: float) -> np.ndarray:
    """The complex field (height, width) `dz_um` further along z (eq. 4: b_n = H b_{n-1})."""
    if field.ndim != 2:
        raise ValueError(f"field must be 2-D (height, width), got shape {field.shape}")
    transfer = fresnel_transfer(frequency_sq_per_um2(field.shape, pixel_um), wavelength_um, dz_um)
    return fft.ifft2(transfer * fft.fft2(field, norm="ortho"), norm="ortho")


class FoldedGrid:
    """An image's FFT grid folded onto its non-negative frequencies.

    fx^2 + fy^2, and so everything of the filter's that depends on it alone (H of eq. 3, Q
    and P, the gain: Lemma 1's symmetry), is the same at (+-fy, +-fx): a quarter array of
    shape (height // 2 + 1, width // 2 + 1) holds every value. `multiply` applies such a
    quarter to a full (height, width) spectrum, or to an rfft's half (height, width // 2 + 1),
    in place through strided views, so the full grid is never expanded: a quarter of the
    element-wise work and of the memory.
    """

    def __init__(self, shape: tuple[int, int], pixel_um: float) -> None:
        if len(shape) != 2 or min(shape) < 1:
            raise ValueError(f"shape must be (height, width) with both >= 1, got {shape}")
        if not pixel_um > 0:
            raise ValueError(f"pixel_um must be > 0, got {pixel_um}")
        height, width = shape
        self.shape = shape
        fy = np.arange(height // 2 + 1) / (height * pixel_um)
        fx = np.arange(width // 2 + 1) / (width * pixel_um)
        #: fx^2 + fy^2 (1/um^2), (height // 2 + 1, width // 2 + 1): the FFT's bins with
        #: fx, fy >= 0 (fftfreq's values, up to the sign).
        self.freq_sq_per_um2 = np.add.outer(fy * fy, fx * fx)
        self._rows = _mirrored(height)
        self._cols = _mirrored(width)
        self._row_weights = _multiplicity(height)
        self._col_weights = _multiplicity(width)

    def multiply(self, spectrum: np.ndarray, quarter: np.ndarray) -> None:
        """spectrum *= the quarter's values at each bin's |fy|, |fx|, in place; spectrum is
        (height, width) or an rfft's (height, width // 2 + 1)."""
        full_width = spectrum.shape[1] == self.shape[1]
        cols = self._cols if full_width else ((slice(None), slice(None)),)
        for spectrum_rows, quarter_rows in self._rows:
            for spectrum_cols, quarter_cols in cols:
                block = spectrum[spectrum_rows, spectrum_cols]
                block *= quarter[quarter_rows, quarter_cols]

    def expand(self, quarter: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The full (height, width) array of a quarter's values (written into `out`, of
        that shape, when given)."""
        full = np.empty(self.shape, dtype=quarter.dtype) if out is None else out
        for full_rows, quarter_rows in self._rows:
            for full_cols, quarter_cols in self._cols:
                full[full_rows, full_cols] = quarter[quarter_rows, quarter_cols]
        return full

    def mean(self, quarter: np.ndarray) -> float:
        """The mean over the full grid of a quarter's values (each counted as often as it
        appears)."""
        # Weights of the quarter's own precision: a float32 quarter (the filter's) takes
        # BLAS's sgemv, no float64 copy; its noise term needs no more than float32's sum.
        dtype = quarter.real.dtype
        total = self._row_weights.astype(dtype) @ quarter @ self._col_weights.astype(dtype)
        return float(total) / (self.shape[0] * self.shape[1])


def _mirrored(n: int) -> tuple[tuple[slice, slice], ...]:
    """(full axis, folded axis) slice pairs: bins 0..n//2 are the folded ones; bins above
    n//2 hold the frequencies -(n - bin), found at folded index n - bin, in reverse."""
    half = n // 2
    return (
        (slice(0, half + 1), slice(0, half + 1)),
        (slice(half + 1, n), slice(n - 1 - half, 0, -1)),
    )


def _multiplicity(n: int) -> np.ndarray:
    """How many bins of an axis of n fold onto each folded index (1 or 2)."""
    weights = np.ones(n // 2 + 1)
    weights[1 : n - n // 2] += 1
    return weights
