"""The sparse augmented complex extended Kalman filter (Zhong, Dauwels, Vazquez, Waller 2013).

The state is b_n, the unitary 2-D Fourier transform of the complex field a_n at plane n
(eqs. 1-4); the observation is the intensity image I_n = gamma |a_n|^2 + v (eq. 5), with
gamma the photons a pixel detects on average, so |a|^2 is the intensity relative to the
stack's mean. The augmented model (eqs. 7-9) has covariance S^Q and pseudo-covariance S^P;
with the weak-object approximation of Theorem 1 both stay diagonal (S^Q = Q, S^P = P E), so
Q and P are stored as vectors (here arrays of the image's shape) and every step is O(N)
apart from the FFTs: Table 1, eqs. 27-33.

Beyond the paper's equal steps from focus, a plane may sit at any known z (either side of
focus, any order): the step n-1 -> n propagates by z_n - z_{n-1} (eq. 3 with that dz).
The planes are filtered from focus outward, the side above focus first (`plane_order`),
so the result does not depend on the order they are given in, and the last estimate is
propagated back to z = 0.

Beyond the paper, four changes, each measured by `focustrack bench phase`:
- the update in the field's own phase frame (`AcekfOptions.update`): eq. 33 divides the
  residual by a_hat^*, which matches Theorem 1's diagonal gain only where the phase is
  small; applying the gain to the residual over |a_hat| and rotating the correction by
  the field's local phase afterwards keeps the weak-object condition true locally (three
  real DFTs, about one and a half complex ones, more per plane; on a 0.5 rad object at
  1000 photons it takes the phase error from 0.062 to 0.022 rad);
- the measurement noise gains the variance of the second-order term the linearisation
  drops, so a confident early plane cannot blow up the update at high photon counts;
- partial coherence (`AcekfOptions.condenser_na`): a disk source damps the intensity's
  linear response at defocus z by 2 J1(v)/v, v = 2 pi z NA_c |f|; the gain and the
  predicted intensity carry that envelope;
- the lowest frequencies, which the stack barely sees, anchored after the filter to the
  slide's empty background (`AcekfOptions.background`, `focustrack_phase.background`):
  where there is glass, most of the low-frequency shadow the paper shows goes, and the
  phase's zero is the medium's.

Memory: the filter holds b, H and three float32 images at the image's size, and a_hat
(eq. 33: a copy of b; ours: b itself, transformed in place and back) or the turned
correction (ours, whose real and imaginary parts are filtered in two of the float32
images), and Q, P, the gain and fx^2+fy^2 on a quarter of the grid (`FoldedGrid`): under
ten arrays of the image's size, besides the stack it reads one frame at a time. Each
full-size image's rows are padded by a few pixels, and its transforms are OpenCV's where
it is installed (`focustrack_phase.transforms`): together they make the FFTs less than
half as costly as scipy.fft's on unpadded images.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from focustrack_phase import transforms
from focustrack_phase.background import anchor_to_background
from focustrack_phase.propagation import FoldedGrid, coherence_envelope, fresnel_transfer

Update = Literal["phase_frame", "paper"]
Background = Literal["anchor", "none"]

#: The largest defocus phase at the image's highest frequency a stack may ask (rad; eq. 3
#: at the grid's corner for the farthest plane, `validate_stack`).
MAX_DEFOCUS_PHASE_RAD = 1e5
#: The least: below it, the farthest plane shows no phase contrast at any frequency the
#: image holds (sin of it < 0.1), and the "phase" is noise (z_um in mm, pixel_um in nm).
MIN_DEFOCUS_PHASE_RAD = 0.1
#: A frame's mean counts must be at least this share of its spread: a background- or
#: mean-subtracted frame, its mean about 0, makes the filter's gamma (eq. 5) meaningless.
MIN_MEAN_OVER_SPREAD = 0.01
#: The longest wavelength a stack may give, um: past the near infrared of any microscope's
#: light, and short of 532, the green laser's wavelength written in nm by mistake.
MAX_WAVELENGTH_UM = 20.0
#: The widest prior, q0 (AcekfOptions): the field's mean intensity is 1, so a departure from
#: the plane wave of variance 1 per Fourier coefficient is already as strong as the field
#: itself. Wider, the gain's denominator q + mean(Q)^2 (`_filtered_field`) grows as q0^2
#: and swamps the update: the phase comes out flat (a 128-pixel weak object's phase
#: spread, 0.36 rad, falls to under 0.09 at q0 = 30 and under 0.003 at 1000). 10 is the
#: widest that `focustrack bench phase` tunes (FILTER_Q0).
MAX_Q0 = 10.0
#: The narrowest: a departure of 1e-4 (rad, for the phase) per pixel, the shot noise of the
#: best stack (10^6 photons a pixel, 201 frames); narrower, the prior holds the field to
#: the plane wave, and below about 1e-38 (float32's smallest) its phase is exactly flat.
MIN_Q0 = 1e-8
#: The highest amplitude floor (AcekfOptions): the field's mean amplitude is 1, so above it
#: every pixel would be clipped and the update divided by the floor alone.
MAX_AMPLITUDE_FLOOR = 1.0
#: The longest prior correlation length, um: a centimetre, past any slide's field of view.
MAX_PRIOR_LENGTH_UM = 1e4
#: The fewest photons a pixel may detect per frame on average (gamma, eq. 5): below, the
#: noise variance 1/gamma (eq. 31) dwarfs any phase contrast and the filter's gain, in
#: single precision, is nothing (a flat phase) or runs away. The bench's sparsest setting,
#: the paper's, is gamma = 0.998.
MIN_GAMMA_PHOTONS = 1e-3


@dataclass(frozen=True)
class AcekfOptions:
    """The filter's prior, its update and the illumination (|a|^2 relative to the mean).

    q0: Q_0 = q0 U, the prior variance of each Fourier coefficient of the field's departure
        from a plane wave (with the unitary FFT, the variance per pixel of a white prior).
    p0: P_0 = p0 U, its prior pseudo-variance: q0 = var(amplitude) + var(phase) and
        p0 = var(amplitude) - var(phase) per coefficient, so p0 < 0 says "mostly phase".
    update: "phase_frame" (ours) applies eq. 33's gain to the residual in the frame of the
        field's own local phase, so Theorem 1's weak-object condition (a close to a real,
        positive field) holds locally even where the phase is not small; "paper" is eq. 33
        as printed (the gain on (I - gamma |a|^2) / a^*, exact only for a weak phase).
    condenser_na: the illumination's numerical aperture (0: coherent, a point source).
        A disk source multiplies the intensity's linear response at defocus z by
        2 J1(v)/v, v = 2 pi z condenser_na |f| (the source average of exp(2 pi i lambda z
        f.s)); the filter's measurement model carries that envelope (beyond the paper).
    amplitude_floor: |a_hat| below this is clipped before dividing by it (eq. 33's
        J_n^-1), so a dark pixel cannot blow up the update.
    prior_length_um: 0 (the paper's white prior) or the correlation length L (um) of a
        smooth prior: Q_0 and P_0 times S(f) = (1 + (2 pi L |f|)^2)^-3/2, the spectrum of
        an object whose phase varies over about L (beyond the paper; still diagonal, so
        Theorem 1 holds). It takes the error on the paper's Data Set 1 from 0.110 to
        about 0.100 rad (`focustrack bench phase`).
    background: "anchor" (the default) re-estimates the lowest frequencies, which the
        stack barely sees, so that the slide's empty background has zero phase
        (`focustrack_phase.background`, beyond the paper: it removes the low-frequency
        shadow), or, where the image has too little background, sets the phase's zero at
        its mean; "none" keeps the filter's own field, as the paper does.

    The defaults hold at every photon count we tried, on the instrument simulator's phase
    specimens up to 2 rad (cells in culture, red cells) at 10^4 photons a pixel, where
    a wider prior (q0 0.05 and up, or p0 < 0) makes the filter run away; on the paper's
    Data Set 1 at one photon `focustrack bench phase` prefers q0 = 1, p0 = -0.9 with
    prior_length_um = 2 (it tunes every method per setting). The paper studied q0 =
    70..7000 and p0 = 50..5000 in its own (unnormalised) units.
    """

    q0: float = 0.01
    p0: float = 0.0
    update: Update = "phase_frame"
    condenser_na: float = 0.0
    amplitude_floor: float = 0.05
    prior_length_um: float = 0.0
    background: Background = "anchor"

    def __post_init__(self) -> None:
        if not MIN_Q0 <= self.q0 <= MAX_Q0:
            raise ValueError(
                f"q0 must be in [{MIN_Q0:g}, {MAX_Q0:g}] (a departure from the plane wave "
                "wider than the field itself, or narrower than any stack measures, flattens "
                f"the phase), got {self.q0}"
            )
        if not abs(self.p0) <= self.q0:
            raise ValueError(f"|p0| must be <= q0 (a covariance), got p0={self.p0}, q0={self.q0}")
        if self.update not in ("phase_frame", "paper"):
            raise ValueError(f"update must be 'phase_frame' or 'paper', got {self.update!r}")
        if not 0 <= self.condenser_na < 1.5:
            raise ValueError(f"condenser_na must be in [0, 1.5), got {self.condenser_na}")
        if not 0 <= self.prior_length_um <= MAX_PRIOR_LENGTH_UM:
            raise ValueError(
                f"prior_length_um must be in [0, {MAX_PRIOR_LENGTH_UM:g}], got "
                f"{self.prior_length_um}"
            )
        if not 0 < self.amplitude_floor <= MAX_AMPLITUDE_FLOOR:
            raise ValueError(
                f"amplitude_floor must be in (0, {MAX_AMPLITUDE_FLOOR:g}] (the field's mean "
                f"amplitude is 1), got {self.amplitude_floor}"
            )
        if self.background not in ("anchor", "none"):
            raise ValueError(f"background must be 'anchor' or 'none', got {self.background!r}")


@dataclass(frozen=True)
class FieldEstimate:
    """The complex field at the plane z = 0 and the photon scale it was estimated with.

    field: complex64 (height, width), dimensionless: |field|^2 is the intensity relative
        to the stack's mean intensity, angle(field) the phase in radians.
    gamma_photons: gamma of eq. 5, the mean photons per pixel of the stack.
    background_share: the share of the image taken as empty glass, whose phase is zero
        (`AcekfOptions.background` "anchor": 0 when there was too little, the zero then
        the phase of the field's mean); None when the field is the filter's own.
    """

    field: np.ndarray
    gamma_photons: float
    background_share: float | None = None

    @property
    def phase_rad(self) -> np.ndarray:
        """Phase (rad), float32 (height, width), in (-pi, pi]."""
        return np.angle(self.field)

    @property
    def amplitude(self) -> np.ndarray:
        """Amplitude (dimensionless, sqrt of the relative intensity), float32 (height, width)."""
        return np.abs(self.field)

    @property
    def intensity(self) -> np.ndarray:
        """Intensity relative to the stack's mean, float32 (height, width)."""
        return np.abs(self.field) ** 2


def nearest_first(z_um: np.ndarray) -> np.ndarray:
    """Indices of the planes by distance from focus, ties by z."""
    return np.lexsort((z_um, np.abs(z_um)))


def plane_order(z_um: np.ndarray) -> np.ndarray:
    """The order the filter visits the planes in: each side of focus from focus outward.

    First z >= 0 by increasing z, then z < 0 by decreasing z: the paper filters from focus
    outward, and equally spaced planes then take one step length per side (plus the jump
    between sides), so one transfer function serves every step.
    """
    above = np.flatnonzero(z_um >= 0)
    below = np.flatnonzero(z_um < 0)
    outward_above = above[np.argsort(z_um[above], kind="stable")]
    outward_below = below[np.argsort(-z_um[below], kind="stable")]
    return np.concatenate([outward_above, outward_below])


def validate_stack(
    stack_counts: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    photons_per_count: float,
) -> tuple[np.ndarray, float]:
    """Check a stack (frames, height, width) and its heights; returns z (um) and gamma.

    Raises ValueError naming what is wrong. gamma (eq. 5) is the stack's mean photons per
    pixel: propagation keeps a field's energy, so every plane has the same mean.
    """
    if not isinstance(stack_counts, np.ndarray) or stack_counts.ndim != 3:
        shape = getattr(stack_counts, "shape", None)
        raise ValueError(f"stack must be a 3-D array (frames, height, width), got shape {shape}")
    frames, height, width = stack_counts.shape
    if frames < 1:
        raise ValueError(f"stack has no frames (shape {stack_counts.shape})")
    if height < 2 or width < 2:
        raise ValueError(f"stack frames must be at least 2x2 pixels, got {height}x{width}")
    if stack_counts.dtype.kind not in "uif":  # not bool, complex, timedelta (an integer to numpy)
        raise ValueError(f"stack must hold real numbers (counts); got dtype {stack_counts.dtype}")
    try:
        z = np.asarray(z_um, dtype=np.float64)
    # ragged lists, strings, integers past float64: numpy's words would name none of them
    except (ValueError, TypeError, OverflowError):
        raise ValueError("z_um must be a flat list of finite numbers (um), one per frame") from None
    if z.ndim != 1 or z.shape[0] != frames:
        got = z.shape[0] if z.ndim == 1 else z.shape
        raise ValueError(f"z_um must list one height per frame: {frames} frames, got {got}")
    if not np.all(np.isfinite(z)):
        raise ValueError("z_um must be finite")
    for name, value in (
        ("wavelength_um", wavelength_um),
        ("pixel_um", pixel_um),
        ("photons_per_count", photons_per_count),
    ):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {value}")
    if not wavelength_um <= MAX_WAVELENGTH_UM:
        raise ValueError(
            f"wavelength_um must be at most {MAX_WAVELENGTH_UM:g} um, got {wavelength_um:g}: "
            "is it in nm?"
        )
    # Eq. 3's phase pi lambda |z| |f|^2 at the grid's corner, |f|^2 = 1 / (2 pixel^2): past
    # MAX_DEFOCUS_PHASE_RAD (over a millimetre of defocus at 0.1 um pixels) the planes'
    # fringes are finer than anything a stack resolves, and the transfer, in single
    # precision, would keep no digit of it; such numbers are a unit gone wrong.
    with np.errstate(over="ignore", divide="ignore"):
        corner_phase_rad = (
            np.pi * wavelength_um * np.max(np.abs(z)) / (2 * np.float64(pixel_um) ** 2)
        )
    if not MIN_DEFOCUS_PHASE_RAD <= corner_phase_rad <= MAX_DEFOCUS_PHASE_RAD:
        bound = (
            f"over the {MAX_DEFOCUS_PHASE_RAD:.0e} rad any stack resolves"
            if corner_phase_rad > MAX_DEFOCUS_PHASE_RAD
            else f"under the {MIN_DEFOCUS_PHASE_RAD:g} rad that shows any phase contrast"
        )
        raise ValueError(
            f"z_um (up to {np.max(np.abs(z)):.3g} um), wavelength_um ({wavelength_um:.3g}) and "
            f"pixel_um ({pixel_um:.3g}) make a defocus phase of {corner_phase_rad:.3g} rad at "
            f"the image's highest frequency, {bound}: are they all in um, the pixel in the "
            "object's plane?"
        )
    # One pass over the stack: a NaN or an inf makes the mean so; only then is every
    # value checked, to say which (finite values whose sum overflows float64).
    with np.errstate(over="ignore", invalid="ignore"):  # said below, in words
        frame_means = np.asarray(np.mean(stack_counts, axis=(1, 2), dtype=np.float64))
        mean_counts = float(np.mean(frame_means))
    if not np.isfinite(mean_counts):
        if not np.all(np.isfinite(stack_counts)):
            raise ValueError("stack must be finite (no NaN or inf)")
        raise ValueError("stack's values are too large: their mean overflows")
    _check_counts_of_light(stack_counts, frame_means)  # so the mean is positive
    gamma = mean_counts * photons_per_count
    if not gamma >= MIN_GAMMA_PHOTONS:
        raise ValueError(
            f"the stack's mean counts ({mean_counts:.3g}) times photons_per_count "
            f"({photons_per_count:.3g}) make {gamma:.3g} photons per pixel per frame, under the "
            f"{MIN_GAMMA_PHOTONS:g} that carries any phase: check photons_per_count (the "
            "camera's gain)"
        )
    return z, gamma


def _check_counts_of_light(stack_counts: np.ndarray, frame_means: np.ndarray) -> None:
    """ValueError at the first frame whose mean is not clearly above 0 against its spread
    (`MIN_MEAN_OVER_SPREAD`): a background- or mean-subtracted frame. Negative counts
    themselves are taken: counts above the camera's offset have them, from read noise. The
    spread is read on every 8th row and column, so the check costs a 64th of a pass."""
    for index, (frame, mean) in enumerate(zip(stack_counts, frame_means.tolist(), strict=True)):
        spread = float(np.std(frame[::8, ::8], dtype=np.float64))
        if not (mean > 0 and mean >= MIN_MEAN_OVER_SPREAD * spread):
            raise ValueError(
                f"frame {index} has a mean of {mean:.4g} counts against a spread of "
                f"{spread:.4g}: the filter takes counts of light (raw, or above the camera's "
                "offset), not background-subtracted or signed frames"
            )


def prior_shape(freq_sq_per_um2: np.ndarray, length_um: float) -> np.ndarray:
    """S(f) = (1 + (2 pi length |f|)^2)^-3/2 (float32, the shape of `freq_sq_per_um2`)."""
    return ((1.0 + (2 * np.pi * length_um) ** 2 * freq_sq_per_um2) ** -1.5).astype(np.float32)


def initial_covariances(
    options: AcekfOptions,
    freq_sq_per_um2: np.ndarray,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Q_0 (float32) and P_0 (complex64) on the folded grid (the shape of `freq_sq_per_um2`).

    By default q0 U and p0 U, times `prior_shape` when the options give a prior length.
    `prior` gives them instead: real Q_0 >= |P_0| of the folded grid's shape, (height // 2
    + 1, width // 2 + 1); folded, they are symmetric in +-fy, +-fx as Lemma 1 needs. With
    Q_0 = |A|^2 + |Phi|^2 and P_0 = |A|^2 - |Phi|^2, the unitary spectra of the object's
    amplitude and phase departures, it is the prior of a filter that knows the object
    (`focustrack bench phase` measures how close that comes to the Wiener estimate).
    """
    if prior is None:
        Q = np.full(freq_sq_per_um2.shape, options.q0, dtype=np.float32)
        P = np.full(freq_sq_per_um2.shape, options.p0, dtype=np.complex64)
        if options.prior_length_um > 0:
            shape_f = prior_shape(freq_sq_per_um2, options.prior_length_um)
            Q *= shape_f
            P *= shape_f
        return Q, P
    Q0, P0 = (np.asarray(covariance) for covariance in prior)
    if Q0.shape != freq_sq_per_um2.shape or P0.shape != freq_sq_per_um2.shape:
        raise ValueError(
            f"prior must be two arrays of the folded grid's shape {freq_sq_per_um2.shape}, "
            f"got {Q0.shape} and {P0.shape}"
        )
    if np.iscomplexobj(Q0) or not (np.all(np.isfinite(Q0)) and np.all(np.isfinite(P0))):
        raise ValueError("prior's Q_0 must be real and both finite")
    if not np.all(np.abs(P0) <= Q0):
        raise ValueError("prior must have Q_0 >= |P_0| everywhere (a covariance)")
    return Q0.astype(np.float32), P0.astype(np.complex64)


def reconstruct(
    stack_counts: np.ndarray,
    z_um: np.ndarray | list[float] | tuple[float, ...],
    wavelength_um: float,
    pixel_um: float,
    photons_per_count: float = 1.0,
    options: AcekfOptions | None = None,
    workers: int = 1,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> FieldEstimate:
    """The complex field at z = 0 from intensity images at heights `z_um` (sparse ACEKF).

    stack_counts: (frames, height, width) raw counts, any real dtype; frame k was taken
        at z_um[k] (um, relative to the plane to reconstruct; either sign, any order).
    wavelength_um, pixel_um: the illumination's wavelength and the pixel pitch in the
        object's plane (um).
    photons_per_count: the camera's gain (photons per count), which sets the noise (q).
    workers: threads of each FFT: 1 takes OpenCV's DFT where it is installed, more
        scipy.fft's with that many threads (`focustrack_phase.transforms`).
    prior: (Q_0, P_0) on the folded grid instead of the options' q0, p0 and prior length
        (`initial_covariances`): a prior that knows the object's spectra, for references.

    The filter runs in single precision (complex64): a phase error of 1e-6 rad is far
    below any noise a camera leaves, and it halves the memory and the time. Per plane the
    paper's update takes one inverse FFT (eq. 30) and one forward (eq. 33). Ours takes the
    same inverse, then filters the real residual by the gain in the field's phase frame
    (`transforms.filter_real`: a real forward DFT and two real inverses, each about half a
    complex one) and takes a forward DFT back to the state: three and a half complex FFTs'
    worth, the least that update allows (docs/phase.md, "The cost of an update"): each
    transform's input needs the previous one's output. Q, P and the gain depend on |f|
    alone, so they live on a quarter of the grid (`FoldedGrid`). With `options.background`
    "anchor" (the default) the phase's lowest frequencies are then set so that the empty
    background is zero (`focustrack_phase.background`). Raises ValueError for bad input,
    FilterDivergedError (a ValueError) when the filter ran away.
    """
    opts = options or AcekfOptions()
    z, gamma = validate_stack(stack_counts, z_um, wavelength_um, pixel_um, photons_per_count)
    field = _filtered_field(
        stack_counts, z, gamma, wavelength_um, pixel_um, photons_per_count, opts, workers, prior
    )
    # The EKF can run away (a prior far wider than the object at a high photon count): its
    # field then overflows. Propagation keeps the mean intensity at 1; say so rather than
    # answer noise.
    with np.errstate(over="ignore", invalid="ignore"):  # an overflowed field: said below
        mean_intensity = float(np.mean(np.abs(field) ** 2, dtype=np.float64))
    if not 0.25 < mean_intensity < 4.0:
        raise FilterDivergedError(
            f"the filter diverged (mean intensity {mean_intensity:.3g} of the stack's, not 1): "
            f"if the heights, the optics and photons_per_count (which make {gamma:.3g} "
            f"photons per pixel) are right, a smaller prior (q0 below {opts.q0:g}) keeps "
            "it stable"
        )
    # (4) Beyond the paper: the lowest frequencies anchored to the empty background, once
    # the filter's working images are freed.
    if opts.background == "none":
        return FieldEstimate(field, gamma)
    anchored = anchor_to_background(field, z, wavelength_um, pixel_um, opts.condenser_na)
    field = np.abs(field) * np.exp(1j * anchored.phase_rad)
    return FieldEstimate(field, gamma, float(np.mean(anchored.background)))


@np.errstate(over="ignore", invalid="ignore", divide="ignore")  # a runaway is caught above
def _filtered_field(
    stack_counts: np.ndarray,
    z: np.ndarray,
    gamma: float,
    wavelength_um: float,
    pixel_um: float,
    photons_per_count: float,
    opts: AcekfOptions,
    workers: int,
    prior: tuple[np.ndarray, np.ndarray] | None,
) -> np.ndarray:
    """The filter itself (Table 1) on a checked stack: the field at z = 0, complex64."""
    shape = stack_counts.shape[1:]
    grid = FoldedGrid(shape, pixel_um)
    freq_sq = grid.freq_sq_per_um2.astype(np.float32)
    q = 1.0 / gamma  # eq. 31: q = 1/gamma, the noise variance of I/gamma per pixel
    photons_to_relative = np.float32(photons_per_count / gamma)
    transfer = _Transfer(grid, freq_sq, wavelength_um)
    floor = np.float32(opts.amplitude_floor)
    # The transforms are unnormalised (`transforms.dft2`, N the pixels): b, the unitary
    # spectrum, is held as dft2(a) / N = b / sqrt(N), which `idft2` turns into a with no
    # product, and the gain's products carry the rest of the unitary pair's 1/N.
    pixels = shape[0] * shape[1]
    # Every working image is a padded buffer (`transforms.padded_zeros`): the FFTs run on
    # its image proper, [inside]; the element-wise passes on the whole buffer.
    inside = np.s_[:, : shape[1]]

    # (1) Initialisation: a plane wave of unit intensity, Q_0 = q0 U, P_0 = p0 U.
    b = transforms.padded_zeros(shape, np.complex64)
    b[0, 0] = 1  # dft2 of a field of ones, over N
    Q, P = initial_covariances(opts, freq_sq, prior)
    # The working images, reused every plane (no allocation in the loop): eq. 33's a_hat,
    # a copy of b_hat transformed in place (ours transforms b_hat itself, below); |a_hat|,
    # the residual and a scratch image; our update's turned correction.
    image = transforms.padded_zeros
    a_hat = image(shape if opts.update == "paper" else (0, 0), np.complex64)
    modulus = image(shape, np.float32)
    residual = image(shape, np.float32)
    scratch = image(shape, np.float32)
    turn = image(shape if opts.update == "phase_frame" else (0, 0), np.complex64)
    z_prev = 0.0
    for k in plane_order(z):
        dz_um = float(z[k]) - z_prev
        z_prev = float(z[k])
        # (2) Prediction; a plane at the previous one's height has H = 1 (eq. 3), none.
        if dz_um != 0:
            H_squared, H_full = transfer.of(dz_um)  # eq. 3
            b *= H_full  # eq. 27: b_hat = H b
            # eq. 28: Q_hat = Q (H Q H^H with |H| = 1)
            P *= H_squared  # eq. 29: P_hat = H P H = H(2 dz) P (H is diagonal)
        # (3) Update. The measurement noise: eq. 31's q, plus the variance of the term the
        # linearisation drops, |a - a_hat|^2, whose per-pixel variance is (mean Q)^2 for a
        # complex Gaussian error (a second-order EKF's correction; without it a confident
        # early plane can blow up the update at high photon counts).
        noise = np.float32(q + grid.mean(Q) ** 2)
        envelope = coherence_envelope(freq_sq, float(z[k]), opts.condenser_na)
        gain = _update_covariances(Q, P, noise, envelope)
        # eq. 30: a_hat = K^H b_hat, in place: on a copy for eq. 33, which adds to b_hat;
        # on b_hat itself for ours, which rebuilds b from the corrected field.
        if opts.update == "paper":
            np.copyto(a_hat, b)
        else:
            a_hat = b
        transforms.idft2(a_hat[inside], workers)
        np.abs(a_hat, out=modulus)
        np.multiply(stack_counts[k], photons_to_relative, out=residual[inside])
        np.square(modulus, out=scratch)
        residual -= scratch  # I / gamma - |a_hat|^2
        # The partially coherent prediction is 1 + E (|a_hat|^2 - 1) in Fourier space, so
        # its residual exceeds the coherent one by (1 - E) (|a_hat|^2 - 1).
        excess = None if envelope is None else scratch - 1
        np.maximum(modulus, floor, out=scratch)  # |a_hat| floored: eq. 33's J_n^-1
        if opts.update == "paper":
            # eq. 33: b += (Q + P) J^-1 q^-1 (I - gamma |a_hat|^2), J^-1 = K diag(1/(gamma
            # a_hat^*)), (Q_n + P_n)/q = `gain`, 1/a_hat^* = a_hat / (|a_hat| |a_hat|_floored).
            np.maximum(modulus, _TINY, out=modulus)  # a_hat = 0 exactly: no 0 / 0
            scratch *= modulus
            residual /= scratch
            weighted_excess = None if excess is None else a_hat * (excess / scratch)
            a_hat *= residual
            innovation = transforms.dft2(a_hat[inside], workers)
            _add_excess(innovation, weighted_excess, envelope, grid, workers)
            gain *= np.float32(1 / pixels)  # the unitary K's 1/sqrt(N), and b's held scale
            grid.multiply(innovation, gain)
            b += a_hat  # the innovation, in a_hat's buffer
            continue
        # Ours: J^-1 = diag(e^{i theta}) diag(1/|a_hat|); applying the gain between the two
        # factors is eq. 33 for the field e^{-i theta} a, which is real and positive at
        # a_hat: Theorem 1's weak object, whatever the phase theta.
        residual /= scratch
        added = None
        if excess is not None and envelope is not None:
            excess /= scratch
            added = (excess[inside], 1 - envelope)
        # The correction c = K^H gain K (residual) (K's pair: 1/N), as c_re + i c_im in the
        # residual and scratch images, over N once more (b's scale, below).
        gain *= np.float32(1 / pixels) ** 2
        transforms.filter_real(
            residual[inside], scratch[inside], gain, grid, added, workers, turn[inside]
        )
        # e^{i theta} = a_hat / |a_hat|: the corrected field a_hat + e^{i theta} c is a_hat
        # (1 + c / |a_hat|), and b_n = K (that field) (K is linear: b_hat needs no copy),
        # held over N.
        np.maximum(modulus, _TINY, out=modulus)
        np.reciprocal(modulus, out=modulus)
        residual *= modulus
        np.add(residual, np.float32(1 / pixels), out=turn.real)
        np.multiply(scratch, modulus, out=turn.imag)
        a_hat *= turn
        transforms.dft2(a_hat[inside], workers)
    # Back-propagation to the focal plane: H(-z_last) = H(z_last)^*.
    b *= transfer.of(-z_prev)[1]
    return transforms.idft2(b[inside], workers)


class FilterDivergedError(ValueError):
    """The sparse ACEKF ran away: its field's intensity left any plausible range."""


def _add_excess(
    spectrum: np.ndarray,
    weighted_excess: np.ndarray | None,
    envelope: np.ndarray | None,
    grid: FoldedGrid,
    workers: int,
) -> None:
    """spectrum += (1 - E) FFT(excess) with partial coherence, in place (complex64 (height,
    width); `weighted_excess`, a padded buffer, is spent)."""
    if weighted_excess is not None and envelope is not None:
        excess_spectrum = transforms.dft2(weighted_excess[:, : spectrum.shape[1]], workers)
        grid.multiply(excess_spectrum, 1 - envelope)
        spectrum += excess_spectrum


def _update_covariances(
    Q: np.ndarray, P: np.ndarray, noise: np.float32, envelope: np.ndarray | None
) -> np.ndarray:
    """Eqs. 31-32 in place on Q (float32) and P (complex64); returns the gain (complex64).

    Both share (Q_hat + P_hat)(2 Re(Q_hat + P_hat) + q)^-1; Q_hat is real, so
    (Q_hat + P_hat^*) = (Q_hat + P_hat)^*, and gain (Q_hat + P_hat)^* = |Q_hat + P_hat|^2 /
    (2 Re(Q_hat + P_hat) + q) is real. With partial coherence the measurement matrix gains
    the envelope E (real): the gain is E (Q + P) / (2 E^2 Re(Q + P) + q) and each update
    takes E once more.
    """
    gain = Q + P  # Q_hat + P_hat, turned into the gain in place below
    squared = None if envelope is None else envelope * envelope
    inverse = 2 * gain.real  # becomes 1 / (2 E^2 Re(Q_hat + P_hat) + q)
    if squared is not None:
        inverse *= squared
    inverse += noise
    np.reciprocal(inverse, out=inverse)
    weight = inverse if squared is None else squared * inverse
    change = np.abs(gain)
    np.square(change, out=change)
    change *= weight
    Q -= change  # eq. 31 (with H_n E)
    pseudo = gain * gain
    pseudo *= weight
    P -= pseudo  # eq. 32 (with H_n E)
    # The pair's covariance [[Q, P], [P^*, Q]] has eigenvalues Q +- |P|. Where a plane has
    # pinned one direction, Q - |P| -> 0 and single precision's round-off can take it
    # below: raise Q to |P| (a little more doubt, never a negative variance that would
    # turn the next gain around).
    np.abs(P, out=change)
    np.maximum(Q, change, out=Q)
    gain *= inverse if envelope is None else envelope * inverse
    return gain


class _Transfer:
    """H(dz) (complex64, eq. 3) of the latest step length, computed again only when it changes.

    `plane_order` makes equally spaced planes take one step length per side of focus, so
    one exponential serves nearly every step. It is held as P needs it, H^2 = H(2 dz) on
    the folded grid (eq. 29), and expanded for b (eq. 27), padded as b is, whose product
    runs faster on a contiguous H.
    """

    def __init__(self, grid: FoldedGrid, freq_sq_per_um2: np.ndarray, wavelength_um: float):
        self._grid = grid
        self._freq_sq = freq_sq_per_um2
        self._wavelength_um = wavelength_um
        self._dz_um: float | None = None
        self._squared = self._full = np.empty(0, dtype=np.complex64)

    def of(self, dz_um: float) -> tuple[np.ndarray, np.ndarray]:
        """H(dz)^2 on the folded grid and H(dz) on the full grid (padded)."""
        if dz_um != self._dz_um:
            self._squared = self._full = np.empty(0, dtype=np.complex64)  # free the old ones
            self._squared = fresnel_transfer(self._freq_sq, self._wavelength_um, 2 * dz_um)
            H = fresnel_transfer(self._freq_sq, self._wavelength_um, dz_um)
            self._full = transforms.padded_zeros(self._grid.shape, np.complex64)
            self._grid.expand(H, out=self._full[:, : self._grid.shape[1]])
            self._dz_um = dz_um
        return self._squared, self._full


_TINY = np.finfo(np.float32).tiny
