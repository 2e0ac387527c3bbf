"""The phase's lowest frequencies anchored to the slide's empty background (beyond the paper).

A through-focus stack sees a weak phase at spatial frequency f through the weak-object
transfer 2 sin(pi lambda z |f|^2) (times the coherence envelope; `phase_transfer_power`).
At the lowest frequencies that is near zero on every plane of a short stack, so the
filter's prior decides them, and a cell's bulk phase comes out as a shadow tens of um
wide: the paper's low-frequency noise, which it puts down to partial coherence. A slide of
unstained cells has what the stack lacks: empty background, whose phase is the mounting
medium's. `anchor_to_background` finds it (`background_mask`: where the field is locally
flat) and re-estimates only the frequencies the stack barely sees (those below the lowest
at which T(f) reaches BAND_SHARE of its highest) so that the background's phase is zero,
each held to the filter's estimate in proportion to what the stack saw there:

    minimise  sum_{n in background} (phi_n + c_n)^2 + sum_f (weight T(f) + RIDGE) |c_hat(f)|^2

over corrections c within that band (c_hat: the unitary FFT of c), by conjugate gradients
(`low_frequency_correction`). The texture that finds the background spreads past a cell's
edge, so this first background stops short of the glass nearest the cells, the glass
that pins a cell's bulk phase best; once anchored, the phase itself tells glass from cell
up to the edge (`background_from_phase`: cells stand above the glass), and the phase is
anchored again to that background. The phase's zero becomes the medium's, the reference a
dry-mass measurement needs. A field with too little background (a confluent layer, a
tissue section), or whose "background" the phase shows to be the flat inside of cells,
is left as the filter gave it, its zero the phase of its mean.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage
from scipy.sparse.linalg import LinearOperator, cg

from focustrack_phase import transforms
from focustrack_phase.propagation import phase_transfer_power

log = logging.getLogger(__name__)

#: The band re-estimated: the frequencies below the lowest at which the transfer power T(f)
#: reaches this share of its highest (partial coherence damps it at high frequencies).
BAND_SHARE = 0.5
#: The filter's estimate's hold against the background, per unit of T(f): chosen (0.3 of
#: 0.3 and 1, and the texture scales below of four sets) by the mean error on the
#: instrument simulator's phase tiles of seeds 2 and 4; `focustrack bench phase` reports
#: seeds 1 and 3.
WEIGHT = 0.3
#: A floor under the penalty, so a frequency that neither the stack nor the background
#: sees (deep inside a wide cell) keeps the filter's estimate.
RIDGE = 1e-7
#: Texture scales (um, and the least in pixels where pixels are coarser): the field less its
#: Gaussian blur of TEXTURE_UM, its power averaged over ENERGY_UM; cells are grown by
#: MARGIN_UM, the width of their defocus fringes. Chosen with WEIGHT.
TEXTURE_UM, TEXTURE_PX = 0.5, 1.0
ENERGY_UM, ENERGY_PX = 0.25, 0.5
MARGIN_UM, MARGIN_PX = 0.5, 1.0
#: Cells in the anchored phase: where it stands above the glass by more than this many
#: times the glass's spread (its median absolute deviation, as a standard deviation).
#: Chosen on seeds 2 and 4 with MARGIN_UM as the cells' growth (3 and 4 did as well on
#: them, 4 kept as the farther from 2, at which noise speckles join up and enclose glass).
CELL_NOISE_SIGMAS = 4.0
#: How far (in the same spreads) the rest of the image must lie above the first background
#: on average for the phase to find the background again, or below it to refuse it (the
#: simulator's tiles and the smears lie 12 to 34 above, a conjugated field as far below;
#: the real yeast stack's side above focus, whose texture took the flat insides of cells
#: for glass, 0.7 below: too little to say, so its first background stays).
EVIDENCE_SIGMAS = 2.0
#: Texture power below this share of the strongest counts as none (round-off).
FLAT_POWER_SHARE = 1e-6
#: Least share of the image that must be background to anchor to it.
MIN_BACKGROUND = 0.05
#: Most texture the background may have against the cells' (median powers): above it the
#: field is not two populations (cells and glass) and nothing is anchored.
MAX_TEXTURE_RATIO = 0.25
#: Conjugate gradients' relative residual and its most iterations: 1e-4 leaves the phase
#: within 5e-3 rad of a dense solve (a test holds it there). The cap bounds the cost (each
#: iteration is two FFTs of a grid of at most about 4 MAX_BAND_BINS bins, so 1000 of them
#: take a few tenths of a second at most). Not lower: on Data Set 1 (437 band bins) CG
#: needs more than 100 iterations, and stopped at 100 its phase was 0.085 rad against 0.058
#: converged. Where the glass pins the band loosely CG may still stop at the cap (a 512 px
#: smear at 1.5 rad, 11 planes over +-2 um, 0.5 um pixels, 1000 photons); its partial
#: answer is kept, with a warning (`low_frequency_correction`).
CG_RTOL = 1e-4
CG_MAX_ITERATIONS = 1000
#: The most bins the band's box (2 reach + 1 a side) may hold: past it the band's edge is
#: lowered until it fits. The band is the frequencies the stack barely sees; its lowest
#: (the widest shadows) matter most, and above the lowered edge the filter's estimate
#: stands. Without the cap a tall, narrow or large image (a 512 px field over +-2 um, a
#: 40000 x 2 strip) made the "small" grid the image's size and conjugate gradients ran to
#: its cap: seconds against the filter's tens of milliseconds.
MAX_BAND_BINS = 4096


@dataclass(frozen=True)
class Anchored:
    """A phase image anchored to its background.

    phase_rad: float32 (height, width), radians, zero on the background (or, where there
        was too little background to anchor to, the field's phase relative to the phase of
        its mean).
    background: bool (height, width), the pixels taken as empty background (all False
        when there were too few).
    """

    phase_rad: np.ndarray
    background: np.ndarray

    @property
    def anchored(self) -> bool:
        return bool(self.background.any())


def background_mask(field: np.ndarray, pixel_um: float) -> np.ndarray:
    """Pixels of empty background, bool (height, width), from a complex field at focus.

    Glass is flat where cells have texture: the power of the field less its Gaussian blur
    (TEXTURE_UM), averaged over ENERGY_UM (neither below its pixel floor), is two
    populations on a slide of cells, and Otsu's threshold on its logarithm splits them.
    Cells are grown by MARGIN_UM (their fringes) and their holes filled (a red cell's flat
    centre is cell, not glass), the image's outermost pixels left open. All False when
    the background is under MIN_BACKGROUND of the image or not much flatter than the
    cells (MAX_TEXTURE_RATIO): no two populations to tell apart.
    """
    if field.ndim != 2:
        raise ValueError(f"field must be 2-D (height, width), got shape {field.shape}")
    detail = field - _blur(field, max(TEXTURE_UM / pixel_um, TEXTURE_PX))
    power = _blur(np.abs(detail) ** 2, max(ENERGY_UM / pixel_um, ENERGY_PX))
    # A flat field, nothing to tell glass from cells, or one whose texture is so faint (a
    # prior longer than the image flattens it) that its floor below would underflow in
    # single precision (log(0)): round-off of a field of unit intensity either way.
    if not power.max() > np.finfo(power.dtype).tiny / FLAT_POWER_SHARE:
        return np.zeros(field.shape, dtype=bool)
    # Below a millionth of the strongest texture is the FFT blur's round-off in single
    # precision (even below zero): flat, as far as the field can tell.
    log_power = np.log(np.maximum(power, FLAT_POWER_SHARE * power.max()))
    background = _around(log_power > otsu_threshold(log_power), pixel_um)
    if background.mean() < MIN_BACKGROUND or not (~background).any():
        return np.zeros(field.shape, dtype=bool)
    if np.median(power[background]) > MAX_TEXTURE_RATIO * np.median(power[~background]):
        return np.zeros(field.shape, dtype=bool)
    return background


def background_from_phase(
    phase_rad: np.ndarray, background: np.ndarray, pixel_um: float
) -> np.ndarray:
    """The background found again in a phase image anchored to a first `background`, bool
    (height, width): the first where the phase does not say clearly, none where it says
    the first was no background.

    A cell's optical path is longer than the medium's, so its phase stands above the
    glass's. Where the rest of the image lies above the first background on average by
    more than EVIDENCE_SIGMAS times that background's spread, cells are where the phase
    stands above it by more than CELL_NOISE_SIGMAS spreads, grown and their holes filled
    as in `background_mask` (unlike texture, which spreads a fringe's width and more past
    a cell's edge, a cell's phase ends at its edge), and the background is what is left
    (the first, where that would be under MIN_BACKGROUND). Where the rest lies below it
    by as much, that was no glass but the flat inside of cells (texture cannot tell the
    two apart), or the stack's heights were given with the wrong sign (which conjugates
    the field): no background.
    """
    if not background.any() or background.all():
        return background
    glass_rad = phase_rad[background]
    level_rad = np.median(glass_rad)
    spread_rad = 1.4826 * np.median(np.abs(glass_rad - level_rad))  # a Gaussian's sigma
    above_rad = np.mean(phase_rad[~background]) - level_rad
    if not np.isfinite(above_rad + spread_rad) or abs(above_rad) <= EVIDENCE_SIGMAS * spread_rad:
        return background
    if above_rad < 0:
        return np.zeros(phase_rad.shape, dtype=bool)
    found = _around(phase_rad - level_rad > CELL_NOISE_SIGMAS * spread_rad, pixel_um)
    return found if found.mean() >= MIN_BACKGROUND else background


def _around(cells: np.ndarray, pixel_um: float) -> np.ndarray:
    """The background around `cells` (bool (height, width)): the pixels neither within
    MARGIN_UM of a cell (its fringes) nor enclosed by cells (a red cell's flat centre is
    cell, not glass)."""
    cells = ndimage.binary_dilation(cells, iterations=round(max(MARGIN_UM / pixel_um, MARGIN_PX)))
    # Holes are filled with the image's outermost pixels open: the filter's periodic model
    # leaves texture along the edges (a slide does not wrap around), which would otherwise
    # enclose the glass that reaches them as a hole. (A wider open band, tried, took the
    # centres of red cells cut by the edge for glass.)
    opened = cells.copy()
    opened[[0, -1], :] = opened[:, [0, -1]] = False
    return ~(ndimage.binary_fill_holes(opened) | cells)


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """The threshold that maximises the between-class variance of `values` (Otsu 1979)."""
    counts, edges = np.histogram(values, bins)
    centres = (edges[:-1] + edges[1:]) / 2
    below = np.cumsum(counts)[:-1]  # a threshold after each bin but the last
    above = counts.sum() - below
    sum_below = np.cumsum(counts * centres)[:-1]
    mean_below = sum_below / np.maximum(below, 1)
    mean_above = (np.sum(counts * centres) - sum_below) / np.maximum(above, 1)
    between = below * above * (mean_below - mean_above) ** 2
    return float(edges[1:-1][np.argmax(between)])


def anchor_to_background(
    field: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    condenser_na: float = 0.0,
    weight: float = WEIGHT,
) -> Anchored:
    """The phase of `field` (complex, (height, width), at focus) with its lowest
    frequencies re-estimated so that its background is zero (module docstring).

    z_um, wavelength_um, condenser_na: the stack the field came from (what it saw, T(f)).
    """

    def anchored(glass: np.ndarray) -> np.ndarray:
        """The phase (float32, radians) corrected so that `glass` is zero, or relative to
        the phase of its mean where `glass` is empty."""
        found = bool(glass.any())
        # The phase is read relative to the glass's mean phasor (the whole image's where
        # there is none), so a phase offset of the field cannot wrap the glass across +-pi.
        reference = np.mean(field[glass] if found else field, dtype=np.complex128)
        turn = np.complex64(np.conj(reference) / max(abs(reference), np.finfo(np.float32).tiny))
        phase_rad = np.angle(field * turn).astype(np.float32)
        if found:
            phase_rad += low_frequency_correction(
                phase_rad, glass, z_um, wavelength_um, pixel_um, condenser_na, weight
            )
        return phase_rad

    background = background_mask(field, pixel_um)
    if background.any():  # anchored to the texture's background, then to the phase's
        background = background_from_phase(anchored(background), background, pixel_um)
    return Anchored(anchored(background), background)


def low_frequency_correction(
    phase_rad: np.ndarray,
    background: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    condenser_na: float = 0.0,
    weight: float = WEIGHT,
) -> np.ndarray:
    """c (float32, (height, width), radians): the least-squares correction of the module
    docstring, limited to the band (`band_edge_per_um`).

    The unknowns are c's unitary Fourier coefficients in the band, theta; with M the
    background's indicator and B the unitary inverse FFT from the band, the normal equations

        (B^H diag(M) B + diag(weight T + RIDGE)) theta = -B^H (M phi)

    are Hermitian positive definite, and conjugate gradients solve them. B^H diag(M) B is
    a convolution of theta with M's spectrum, which couples band bins at most twice the
    band's reach apart: on a small grid of at least 4 reach + 1 bins a side, holding M's
    spectrum cropped to those differences, the circular convolution is the same matrix
    (no product wraps onto the band), so each iteration is two FFTs of that small grid.
    c comes back to the full grid by zero-padding its spectrum (exact: c is band-limited).
    """
    height, width = phase_rad.shape
    edge_per_um = band_edge_per_um((height, width), z_um, wavelength_um, pixel_um, condenser_na)
    reach_y, reach_x = _reaches(edge_per_um, (height, width), pixel_um)
    while (box := (2 * reach_y + 1) * (2 * reach_x + 1)) > MAX_BAND_BINS:
        # Lower the edge (MAX_BAND_BINS): by the square root of the excess, as both reaches
        # scale with it (the loop finishes what a reach cut at a quarter leaves).
        edge_per_um *= np.sqrt(MAX_BAND_BINS / box)
        reach_y, reach_x = _reaches(edge_per_um, (height, width), pixel_um)
    within = np.ix_(_bins(reach_y, height), _bins(reach_x, width))
    freq_sq = np.add.outer(
        fft.fftfreq(height, pixel_um)[within[0].ravel()] ** 2,
        fft.fftfreq(width, pixel_um)[within[1].ravel()] ** 2,
    )
    band = freq_sq < edge_per_um**2
    transfer = phase_transfer_power(freq_sq[band], z_um, wavelength_um, condenser_na)
    penalty = weight * transfer + RIDGE
    # M's spectrum at the differences of two band bins, on the small grid; scaled so that
    # the small grid's (unnormalised) circular convolution is the full grid's (the unitary
    # spectrum times sqrt(mask.size) is the unnormalised one, which `_spectrum` gives).
    mask = background.astype(np.float32)
    small = (fft.next_fast_len(4 * reach_y + 1), fft.next_fast_len(4 * reach_x + 1))
    differences = np.ix_(_bins(2 * reach_y, height), _bins(2 * reach_x, width))
    cropped = _spectrum(mask)[differences] * (small[0] * small[1] / mask.size)
    mask_spectrum = np.zeros(small, dtype=np.complex64)
    mask_spectrum[np.ix_(_bins(2 * reach_y, small[0]), _bins(2 * reach_x, small[1]))] = cropped
    small_mask = fft.ifft2(mask_spectrum, overwrite_x=True)
    # The band's bins as flat indices of the small grid: theta goes in and comes out in one
    # put and one take. The products run in single precision, ample for CG_RTOL.
    on_small = np.add.outer(_bins(reach_y, small[0]) * small[1], _bins(reach_x, small[1]))[band]

    def normal(theta: np.ndarray) -> np.ndarray:
        spectrum = np.zeros(small, dtype=np.complex64)
        spectrum.ravel()[on_small] = theta
        product = fft.fft2(small_mask * fft.ifft2(spectrum, overwrite_x=True), overwrite_x=True)
        return product.ravel()[on_small] + penalty * theta

    unitary = 1 / np.sqrt(mask.size)  # the unitary FFT's factor on the unnormalised DFT
    rhs = -_spectrum(np.where(background, phase_rad, np.float32(0)))[within][band] * unitary
    size = int(band.sum())
    diagonal = float(mask.mean()) + penalty  # B^H diag(M) B's diagonal is M's mean
    theta, info = cg(
        LinearOperator((size, size), matvec=normal, dtype=complex),
        rhs,
        rtol=CG_RTOL,
        maxiter=CG_MAX_ITERATIONS,
        M=LinearOperator((size, size), matvec=lambda r: r / diagonal, dtype=complex),
    )
    if info != 0:
        # Kept, not dropped: from theta = 0 (no correction) every conjugate-gradient step
        # lowers the least squares' objective (the module docstring's; CG minimises it over
        # a growing Krylov space), so an unfinished solve is still nearer the answer than
        # no correction is. Said, so a slow solve is seen.
        log.warning(
            "the background anchoring's conjugate gradients stopped unconverged after %d "
            "iterations (%d band bins, %.3g of the image background): its correction is "
            "partial",
            info,
            size,
            float(mask.mean()),
        )
    correction = transforms.padded_image((height, width), np.complex64)
    correction[within] = _scatter(theta * unitary, band)
    return transforms.idft2(correction).real


def band_edge_per_um(
    shape: tuple[int, int],
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    condenser_na: float = 0.0,
) -> float:
    """The band's edge (cycles/um): the lowest frequency of an image of `shape` at which
    the stack's transfer power T(f) reaches BAND_SHARE of its highest (T depends on |f|
    alone, so it is read along a radius, in steps of the image's finest bin)."""
    step_per_um = 1.0 / (max(shape) * pixel_um)
    radius_per_um = np.arange(0.0, np.hypot(0.5, 0.5) / pixel_um + step_per_um, step_per_um)
    transfer = phase_transfer_power(radius_per_um**2, z_um, wavelength_um, condenser_na)
    return float(radius_per_um[np.argmax(transfer >= BAND_SHARE * transfer.max())])


def _blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """`image` (height, width) convolved with a periodic Gaussian of `sigma_px`, by FFT
    (one forward and one inverse transform whatever the width); complex64 for a complex
    image, float32 otherwise."""

    def gaussian(freqs: np.ndarray) -> np.ndarray:  # its transform, exp(-2 pi^2 s^2 f^2)
        return np.exp(-2 * (np.pi * sigma_px) ** 2 * freqs**2).astype(np.float32)

    rows = gaussian(fft.fftfreq(image.shape[0]))[:, None]  # separable: two small factors
    if np.iscomplexobj(image):
        spectrum = transforms.dft2(_padded_copy(image))
        spectrum *= rows / np.float32(image.size)  # and the DFT pair's 1/N
        spectrum *= gaussian(fft.fftfreq(image.shape[1]))
        return transforms.idft2(spectrum)
    half = fft.rfft2(image.astype(np.float32))
    half *= rows
    half *= gaussian(fft.rfftfreq(image.shape[1]))
    return fft.irfft2(half, s=image.shape, overwrite_x=True)


def _spectrum(image: np.ndarray) -> np.ndarray:
    """The unnormalised DFT (complex64, (height, width)) of a real float32 image."""
    return transforms.dft2(_padded_copy(image))


def _padded_copy(image: np.ndarray) -> np.ndarray:
    """A complex64 copy of an image (height, width) in a padded working image."""
    copy = transforms.padded_image(image.shape, np.complex64)
    copy[...] = image
    return copy


def _reaches(edge_per_um: float, shape: tuple[int, int], pixel_um: float) -> tuple[int, int]:
    """The band's reach in bins from zero frequency along each axis of an image of `shape`
    (a band past a quarter of the grid, which only a stack of a few um on a small image
    has, is cut there, so the small grid's 4 reach + 1 bins fit in the image's)."""
    height, width = shape
    return (
        min(int(edge_per_um * height * pixel_um), (height - 1) // 4),
        min(int(edge_per_um * width * pixel_um), (width - 1) // 4),
    )


def _bins(reach: int, size: int) -> np.ndarray:
    """Indices of the FFT bins -reach .. reach of a grid of `size` bins (reach < size / 2)."""
    return np.r_[0 : reach + 1, size - reach : size]


def _scatter(theta: np.ndarray, band: np.ndarray) -> np.ndarray:
    """The band's coefficients `theta` on the bins within reach (zero outside the band)."""
    within = np.zeros(band.shape, dtype=complex)
    within[band] = theta
    return within
