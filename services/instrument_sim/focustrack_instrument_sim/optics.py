"""Defocus blur of a brightfield microscope, from NA, wavelength, magnification and camera pixel.

Imaging is incoherent (condenser aperture filled), so a defocused frame is the
in-focus intensity convolved with the defocused point spread function. The PSF
follows from the pupil (radius NA / lambda) with the Fresnel defocus phase
``exp(-i pi lambda dz rho^2 / n)`` (the paraxial form of the angular-spectrum
transfer function ``exp(i 2 pi dz sqrt((n / lambda)^2 - rho^2))``, Zhong et al.
eq. 3). Fresnel, because the depth-of-field formula below is paraxial too: at NA
0.85 the exact phase defocuses the pupil edge 31% faster and would shorten the
wave-optical depth of field by about a quarter. The pupil is round, so PSF and
OTF are radial and two Hankel transforms, precomputed as matrices, give the OTF of
any defocus in well under a millisecond:

    a(r)  = 2 pi int_0^{NA/lambda} P(rho) exp(i phi(rho, dz)) J0(2 pi rho r) rho d rho
    h(r)  = |a(r)|^2
    H(q)  = 2 pi int_0^inf h(r) J0(2 pi q r) r dr / (same at q = 0)

A frame is then one inverse FFT of the (cached) in-focus spectrum times the OTF.
The FFTs are OpenCV's, on its packed "CCS" layout of real spectra: about twice as
fast as numpy's `irfft2`; `ccs_frequency_indices` says which frequency every
element of that layout holds.

Depth of field (Rayleigh quarter-wave criterion plus one camera pixel of
geometric blur): ``lambda n / NA^2 + n e / (M NA)``.

Phase specimens (unstained cells) absorb almost nothing: incoherent imaging would show
nothing of them at any defocus. They are imaged with partially coherent light instead,
by Abbe's method (`AbbeImager`): one coherent image per point s of the condenser's
aperture (a tilted plane wave), the intensities summed,

    a_s(x) = IFFT[ T(f - s) P(f) exp(-i pi lambda dz |f|^2 / n) ],  I = sum_s w_s |a_s|^2

with T the FFT of the specimen's complex transmittance t(x) (so that T(f - s) is the
spectrum of t(x) exp(i 2 pi s.x)), P the objective's pupil (|f| <= NA / lambda) and the
same paraxial defocus as above (and as the phase service's propagation model).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from focustrack_instrument_sim.instrument import depth_of_field_um
from focustrack_instrument_sim.simulator_options import default

#: Channel order of every rendered image.
CHANNELS = "RGB"


@dataclass(frozen=True)
class Optics:
    """Objective and camera geometry. Lengths in um.

    Defaults: a 60x / 0.85 dry objective with a 6.5 um-pixel camera (0.108 um
    per pixel in the specimen), wavelengths at the centres of the camera's RGB
    filters; the green one is the reference for the depth of field.
    """

    numerical_aperture: float = default("na")
    magnification: float = default("magnification")
    refractive_index: float = 1.0
    camera_pixel_um: float = 6.5
    wavelengths_um: tuple[float, float, float] = (0.61, 0.55, 0.47)  # R, G, B
    max_defocus_um: float = 20.0  # PSF support sized for this defocus; beyond, blur saturates

    def __post_init__(self) -> None:
        if not 0 < self.numerical_aperture < self.refractive_index:
            raise ValueError(
                f"NA must lie in (0, n={self.refractive_index}), got {self.numerical_aperture}"
            )
        if not (self.magnification > 0 and self.camera_pixel_um > 0):
            raise ValueError("magnification and camera pixel must be positive")
        if len(self.wavelengths_um) != len(CHANNELS) or min(self.wavelengths_um) <= 0:
            raise ValueError(f"need {len(CHANNELS)} positive wavelengths (um)")

    @property
    def pixel_size_um(self) -> float:
        """Camera pixel projected into the specimen plane."""
        return self.camera_pixel_um / self.magnification

    @property
    def reference_wavelength_um(self) -> float:
        return self.wavelengths_um[1]

    @property
    def depth_of_field_um(self) -> float:
        """lambda n / NA^2 + n e / (M NA), at the reference (green) wavelength."""
        return depth_of_field_um(
            self.reference_wavelength_um,
            self.refractive_index,
            self.numerical_aperture,
            self.pixel_size_um,
        )


def defocus_phase(wavelength_um: float, refractive_index: float) -> float:
    """-pi lambda / n (rad um): the paraxial (Fresnel) defocus phase of spatial frequency
    rho (cycles/um) at defocus dz (um) is this times rho^2 dz."""
    return -np.pi * wavelength_um / refractive_index


class DefocusOTF:
    """Radial incoherent OTF of one wavelength against defocus, by two Hankel-transform matrices.

    `profile(dz_um)` returns the OTF at spatial frequencies `q_per_um`
    (shape (n_q,), from 0 to the cutoff 2 NA / lambda), with one extra 0 for
    frequencies beyond the cutoff.
    """

    def __init__(
        self,
        optics: Optics,
        wavelength_um: float,
        *,
        n_rho: int = 256,
        n_q: int = 512,
        dr_um: float = 0.05,
    ) -> None:
        # Imported here, when the simulator first renders: the service answers before then.
        from scipy import special

        na, n = optics.numerical_aperture, optics.refractive_index
        self.wavelength_um = wavelength_um
        self._max_dz_um = optics.max_defocus_um
        rho_cut = na / wavelength_um
        d_rho = rho_cut / n_rho
        rho = (np.arange(n_rho) + 0.5) * d_rho  # midpoint rule over the pupil
        # PSF support: the geometric blur radius dz tan(theta) at max defocus, plus the Airy core.
        tan_theta = na / np.sqrt(n * n - na * na)
        r_max_um = optics.max_defocus_um * tan_theta + 10.0 * wavelength_um / na
        r = (np.arange(int(np.ceil(r_max_um / dr_um))) + 0.5) * dr_um
        self.q_per_um = np.linspace(0.0, 2.0 * rho_cut, n_q)
        self.dq_per_um = float(self.q_per_um[1])
        # a = A @ pupil field; H = B @ h (unnormalised); rows of B are frequencies q. float32:
        # the OTF stays within 0.5% of a 4x finer float64 quadrature, at a quarter of the cost.
        kernel_a = special.j0(2.0 * np.pi * np.outer(r, rho)) * (2.0 * np.pi * rho * d_rho)
        kernel_b = special.j0(2.0 * np.pi * np.outer(self.q_per_um, r)) * (2.0 * np.pi * r * dr_um)
        self._A = kernel_a.astype(np.float32)
        self._B = kernel_b.astype(np.float32)
        self._phase_per_um = (defocus_phase(wavelength_um, n) * rho**2).astype(np.float32)

    def profile(self, dz_um: float) -> np.ndarray:
        """OTF at `q_per_um` for defocus `dz_um`, normalised to 1 at q = 0, plus a trailing 0.

        float32, shape (n_q + 1,). Defocus beyond `max_defocus_um` is clipped to it.
        """
        phase = self._phase_per_um * np.float32(np.clip(dz_um, -self._max_dz_um, self._max_dz_um))
        amplitude_re = self._A @ np.cos(phase)
        amplitude_im = self._A @ np.sin(phase)
        otf = self._B @ (amplitude_re**2 + amplitude_im**2)
        return np.append(otf / otf[0], np.float32(0.0))


def check_frame_shape(shape: tuple[int, int]) -> None:
    """ValueError unless (height, width) has even sides of 2 pixels or more (CCS layout)."""
    height, width = shape
    if height % 2 or width % 2 or height < 2 or width < 2:
        raise ValueError(f"frame sides must be even and >= 2, got {shape}")


def ccs_frequency_indices(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(|v|, u): the frequency indices held by each element of OpenCV's CCS spectrum layout.

    For a real (height, width) image with even sides, `cv2.dft` packs the
    spectrum into a real (height, width) array: columns 1..width-2 hold Re/Im
    pairs of u = (c + 1) // 2 at row frequency v = r; the first and last
    columns hold u = 0 and u = width / 2, with v = (r + 1) // 2 packed down the
    rows. Both are int arrays of `shape`; v is folded to |v| <= height / 2.
    """
    check_frame_shape(shape)
    height, width = shape
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    u = np.broadcast_to((cols + 1) // 2, shape).copy()
    v = np.broadcast_to(np.minimum(rows, height - rows), shape).copy()
    edge = np.zeros(width, dtype=bool)
    edge[[0, width - 1]] = True
    v[:, edge] = ((rows + 1) // 2) * np.ones((1, 2), dtype=int)
    return v, u


@dataclass(frozen=True)
class FrameGeometry:
    """Frequency maps of a frame size, in CCS layout, shared by every tile of that size."""

    height: int
    width: int
    pixel_size_um: float

    @cached_property
    def radius_per_um(self) -> np.ndarray:
        """Spatial frequency (cycles/um) of each CCS element, shape (height, width)."""
        v, u = ccs_frequency_indices((self.height, self.width))
        return np.hypot(v / self.height, u / self.width) / self.pixel_size_um

    @cached_property
    def pixel_mtf(self) -> np.ndarray:
        """Transfer function of square pixels integrating their area (fill factor 1)."""
        v, u = ccs_frequency_indices((self.height, self.width))
        return (np.sinc(v / self.height) * np.sinc(u / self.width)).astype(np.float32)

    def bins(self, otf: DefocusOTF) -> np.ndarray:
        """Index into `otf.profile(...)` for each CCS element (nearest q; last = beyond cutoff)."""
        index = np.rint(self.radius_per_um / otf.dq_per_um).astype(np.intp)
        return np.minimum(index, len(otf.q_per_um))


def spectrum(plane: np.ndarray) -> np.ndarray:
    """CCS spectrum (float32, same shape) of a real float32 image plane."""
    return cv2.dft(np.ascontiguousarray(plane, dtype=np.float32))


def blurred(
    spectrum_ccs: np.ndarray, otf_map: np.ndarray, scale: float, out: np.ndarray | None = None
) -> np.ndarray:
    """The image plane whose CCS spectrum is `spectrum_ccs * otf_map`, times `scale`.

    With `out` (float32, the shape of the spectrum), the plane is written there and
    `otf_map` is overwritten by the product: a renderer that keeps both buffers allocates
    nothing per frame (fresh megabyte arrays cost page faults that outweigh the FFT).
    """
    product = cv2.multiply(
        spectrum_ccs, otf_map, dst=None if out is None else otf_map, scale=scale / spectrum_ccs.size
    )
    return cv2.idft(product, dst=out, flags=cv2.DFT_REAL_OUTPUT)


@dataclass(frozen=True)
class Illumination:
    """Brightfield illumination of phase specimens: quasi-monochromatic light (a green
    interference filter) of `wavelength_um`, um, from a condenser aperture of numerical
    aperture `condenser_na` (0: an on-axis point source, coherent light), sampled by
    Abbe's method at its centre and `source_rings` rings of points (`source_offsets`)."""

    wavelength_um: float = 0.532
    condenser_na: float = default("condenser_na")
    source_rings: int = 2

    def __post_init__(self) -> None:
        if not self.wavelength_um > 0:
            raise ValueError(f"the wavelength must be positive, got {self.wavelength_um} um")
        if self.condenser_na < 0 or self.source_rings < 1:
            raise ValueError("the condenser NA must not be negative, nor source rings below 1")


def source_offsets(
    illumination: Illumination, shape: tuple[int, int], pixel_size_um: float
) -> tuple[np.ndarray, np.ndarray]:
    """Abbe's source points as frequency-grid offsets, and their weights.

    The condenser's aperture, a disc of radius condenser_na / lambda (cycles/um), is
    sampled at its centre and on rings k = 1..K (K = `source_rings`) of 6k points at
    radius k / (K + 1/2) of the disc's: each point then stands for about the same area
    of the disc (ring k covers radii (k -+ 1/2) / (K + 1/2)), so the weights are equal.
    Each point is snapped to the nearest frequency of the frame's FFT grid (steps of
    1 / (side * pixel) cycles/um): the tilted plane wave is then periodic over the frame,
    as the FFT assumes. Points that snap together are merged, their weights summed.

    Returns (offsets, weights): int (n, 2) grid offsets (dv, du) along (rows, columns),
    and float64 (n,) weights summing to 1. A condenser NA of 0 gives the one point (0, 0).
    """
    height, width = shape
    radius_per_um = illumination.condenser_na / illumination.wavelength_um
    points = [(0.0, 0.0)]
    rings = illumination.source_rings if radius_per_um > 0 else 0
    for k in range(1, rings + 1):
        ring_per_um = radius_per_um * k / (rings + 0.5)
        angles = 2.0 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
        points.extend(zip(ring_per_um * np.sin(angles), ring_per_um * np.cos(angles), strict=True))
    fy_per_um, fx_per_um = np.array(points).T
    offsets = np.stack(
        [np.rint(fy_per_um * height * pixel_size_um), np.rint(fx_per_um * width * pixel_size_um)],
        axis=1,
    ).astype(np.intp)
    unique, counts = np.unique(offsets, axis=0, return_counts=True)
    return unique, counts / counts.sum()


def band_limited_size(side: int, band_bins: float) -> int:
    """The smallest even FFT size (a product of 2, 3 and 5) above 2 `band_bins`, at most
    `side`: a grid that samples a signal of `band_bins` frequency bins without aliasing."""
    size = cv2.getOptimalDFTSize(int(np.floor(2.0 * band_bins)) + 1)
    while size % 2:
        size = cv2.getOptimalDFTSize(size + 1)
    return min(size, side)


class AbbeWorkspace:
    """One rendering thread's buffers for `AbbeImager.intensity`: `grid` (height, width)
    the coarse grid the fields are computed on, `shape` the frame's."""

    def __init__(self, grid: tuple[int, int], shape: tuple[int, int]) -> None:
        self.spectrum = np.zeros(grid, dtype=np.complex64)  # zero outside the pupil, always
        self.field = np.empty((*grid, 2), dtype=np.float32)  # complex, as OpenCV lays it out
        self.accumulated = np.empty((*grid, 2), dtype=np.float32)
        self.coarse = np.empty(grid, dtype=np.float32)
        # the intensity's half spectrum on the frame's grid: zero beyond its band, always
        self.padded = np.zeros((shape[0], shape[1] // 2 + 1), dtype=np.complex64)


class AbbeImager:
    """Partially coherent brightfield images of a thin complex specimen (see the module's
    doc), frames of `shape` (height, width) with the pixels of `optics` in the specimen
    plane.

    `spectrum(t)` once per tile, then `intensity(spectrum, dz_um)` per frame: relative
    intensity (1: clear glass), float32 (height, width). The intensity is sampled at the
    pixel centres (no pixel integration: the field's band, NA / lambda, and the
    intensity's, twice it, lie within Nyquist at the default 0.108 um pixels). The FFT is
    periodic: a specimen cut at the frame's edge diffracts across it.

    Only the pupil's frequencies are carried: one complex inverse FFT per source point.
    With several source points, each one's field is computed on the coarsest grid over
    the same frame that holds the intensity's band (2 NA / lambda) without aliasing
    (`grid`: 360 x 360 for 512 x 512 frames at the defaults, 720 x 720 for 1024 x 1024),
    and the summed intensity, band-limited, is interpolated exactly onto the frame's
    pixels by zero-padding its spectrum (two real FFTs per frame): 1.4 times faster at
    512 x 512 with 19 points, twice at 1024 x 1024. With one point (coherent light)
    `grid` is the frame's.
    """

    def __init__(self, optics: Optics, illumination: Illumination, shape: tuple[int, int]) -> None:
        check_frame_shape(shape)
        height, width = shape
        self.shape = shape
        pixel_um = optics.pixel_size_um
        fy_per_um = np.fft.fftfreq(height, d=pixel_um)
        fx_per_um = np.fft.fftfreq(width, d=pixel_um)
        f_sq = np.add.outer(fy_per_um**2, fx_per_um**2)
        cutoff_per_um = optics.numerical_aperture / illumination.wavelength_um
        pupil = np.flatnonzero(f_sq <= cutoff_per_um**2)  # P(f) = 1 there, 0 elsewhere
        self._f_sq = f_sq.ravel()[pupil].astype(np.float32)
        self._defocus = defocus_phase(illumination.wavelength_um, optics.refractive_index)
        offsets, weights = source_offsets(illumination, shape, pixel_um)
        # The intensity's band, 2 NA / lambda, in frequency bins of each side.
        grid = (
            band_limited_size(height, 2.0 * cutoff_per_um * height * pixel_um),
            band_limited_size(width, 2.0 * cutoff_per_um * width * pixel_um),
        )
        # The interpolation onto the frame costs about two inverse FFTs of the frame's size:
        # worth it only where the source points save more (measured: not for one point).
        saved = len(offsets) * (1.0 - grid[0] * grid[1] / (height * width))
        self.grid = grid if saved > 2.0 else shape
        v, u = np.divmod(pupil, width)
        v = np.where(v > height // 2, v - height, v)
        u = np.where(u > width // 2, u - width, u)
        self._pupil = (v % self.grid[0]) * self.grid[1] + (u % self.grid[1])  # on the grid
        # T(f - s) at the pupil's frequencies f, for each source point s: indices into T.
        self._gathers = tuple(
            (((v - dv) % height) * width + (u - du) % width) for dv, du in offsets
        )
        # sqrt(w_s) (intensities add with weights w_s) and 1 / (height width): T is the
        # frame's unnormalised DFT, OpenCV's inverse DFT on the grid unnormalised too.
        self._amplitudes = (np.sqrt(weights) / (height * width)).astype(np.float32)

    @property
    def n_sources(self) -> int:
        """Source points after snapping and merging (`source_offsets`)."""
        return len(self._gathers)

    def workspace(self) -> AbbeWorkspace:
        """Buffers for `intensity`, for one thread."""
        return AbbeWorkspace(self.grid, self.shape)

    def spectrum(self, transmittance: np.ndarray) -> np.ndarray:
        """T = FFT(t), complex64 (height, width), of a complex transmittance (height, width)."""
        t = np.ascontiguousarray(transmittance, dtype=np.complex64)
        if t.shape != self.shape:
            raise ValueError(f"transmittance {t.shape} is not of the frame's shape {self.shape}")
        ccs = cv2.dft(t.view(np.float32).reshape(*self.shape, 2), flags=cv2.DFT_COMPLEX_OUTPUT)
        return ccs.view(np.complex64).reshape(self.shape)

    def intensity(
        self,
        spectrum_t: np.ndarray,
        dz_um: float,
        work: AbbeWorkspace | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """The image's relative intensity at defocus `dz_um` (um; 1: clear glass), float32
        (height, width), from `spectrum_t` (`spectrum`), into `out` if given."""
        work = work or self.workspace()
        angle = self._f_sq * np.float32(self._defocus * dz_um)
        transfer = np.empty(angle.shape, dtype=np.complex64)  # exp(-i pi lambda dz |f|^2 / n)
        transfer.real, transfer.imag = np.cos(angle), np.sin(angle)
        flat_t, spectrum_s = spectrum_t.ravel(), work.spectrum.ravel()
        work.accumulated.fill(0.0)
        for gather, amplitude in zip(self._gathers, self._amplitudes, strict=True):
            spectrum_s[self._pupil] = flat_t[gather] * (transfer * amplitude)
            cv2.idft(
                work.spectrum.view(np.float32).reshape(*self.grid, 2),
                dst=work.field,
                flags=cv2.DFT_COMPLEX_OUTPUT,
            )
            cv2.accumulateSquare(work.field, work.accumulated)  # |a_s|^2 = re^2 + im^2
        coarse = np.add(work.accumulated[..., 0], work.accumulated[..., 1], out=work.coarse)
        if self.grid != self.shape:
            return self._interpolated(coarse, work, out)
        if out is None:
            return coarse.copy()
        np.copyto(out, coarse)
        return out

    def _interpolated(
        self, coarse: np.ndarray, work: AbbeWorkspace, out: np.ndarray | None
    ) -> np.ndarray:
        """The band-limited `coarse` image (grid) on the frame's pixels: its half spectrum
        zero-padded to the frame's (Nyquist bins dropped: the band is below them)."""
        (rows, cols), (height, width) = self.grid, self.shape
        half = np.fft.rfft2(coarse)  # (rows, cols // 2 + 1)
        low, high = rows // 2, rows - rows // 2 - 1  # non-negative and negative row frequencies
        work.padded[:low, : cols // 2] = half[:low, : cols // 2]
        work.padded[height - high :, : cols // 2] = half[rows - high :, : cols // 2]
        image = np.fft.irfft2(work.padded, s=self.shape)
        scale = np.float32(height * width / (rows * cols))
        return np.multiply(image, scale, out=out, dtype=np.float32, casting="same_kind")
