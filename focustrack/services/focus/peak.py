"""Best focus from a focus curve: a sub-step peak, an honest standard deviation, and flags.

The peak is refined below the z step by a Gaussian fitted around the best
frame: a least-squares parabola in log(score), whose vertex is the Gaussian's
centre (exact for a Gaussian peak; Caruana's method when three frames are
used). The window holds the frames within half the peak's height above the
curve's floor, at least the best frame and its two neighbours, at most three
each side: on a peak that spans few frames the three-point fit has the least
model bias, on a broad one more frames average the noise.

Its standard deviation has two parts, added in quadrature:
- noise: the score noise (estimated from the curve itself, as the robust
  spread of its third differences: `score_noise`)
  propagated through the weighted fit to the vertex z0 = -b1 / (2 b2) by the
  delta method;
- model: the error of fitting a Gaussian to a peak of another shape with the
  frames at an arbitrary phase: in z steps, a floor plus a part that grows
  as the peak narrows (`PeakSettings.model_sigma_steps / width`), measured
  on noise-free curves.
A curve with more than one peak adds the variance of the choice between
them. The constants are calibrated on simulated stacks so that the z-scores
(error / sigma) have a spread near one (`focustrack bench focus` reports
it; docs/focus.md gives the figures).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.signal import find_peaks

from focustrack.services.estimator.strategy import FocusFlag

_MAD_TO_SIGMA = 1.4826
#: Std of a uniform error over one step: the argmax alone, without any refinement.
_QUANTISATION_STEPS = 1.0 / math.sqrt(12.0)


class PeakMode(StrEnum):
    """Where the focus lies on the curve."""

    MAX = "max"  # the maximum: stained (amplitude) specimens, the usual case
    # the minimum between the two highest maxima: unstained, phase-like specimens in
    # brightfield, whose contrast vanishes in focus and reverses sign across it
    VALLEY = "valley"


@dataclass(frozen=True)
class PeakSettings:
    """How a focus curve is read.

    min_contrast: a curve whose range is below this share of its maximum is flat.
    min_snr: ... or whose peak rises less than this many score-noise sigmas above its floor
        (where the curve is long enough for a clean noise estimate: `score_noise`).
    multi_peak_share: a second local maximum at least this share of the curve's range
        high (prominence) makes the curve multi-peaked.
    noise_scale: the calibration of the noise part of sigma (module docstring).
    model_sigma_steps: the model part of sigma, in z steps, for a peak whose half width at
        half maximum is one step; it scales as 1 / width (narrower peaks are
        sampled by fewer frames), up to the quantisation limit 1 / sqrt(12) step.
    model_floor_steps: the model error, in z steps, that remains however wide the peak
        (an asymmetric window, a curve that is not a Gaussian), added in quadrature.
    """

    mode: PeakMode = PeakMode.MAX
    min_contrast: float = 0.01
    min_snr: float = 10.0
    multi_peak_share: float = 0.25
    noise_scale: float = 1.0
    model_sigma_steps: float = 0.06
    model_floor_steps: float = 0.07


@dataclass(frozen=True)
class PeakFit:
    """The focus read from a curve, in um. z_um and sigma_um are None where there is none.

    For an edge peak z_um is the edge frame's z and sigma_um None: the focus is
    beyond the range, in the direction the flag says.
    """

    z_um: float | None
    sigma_um: float | None
    flags: frozenset[FocusFlag]

    @property
    def is_observation(self) -> bool:
        return self.sigma_um is not None


def validate_curve(z_um: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check a curve and sort it by z; ValueError saying what is wrong. Shapes (n,), n >= 3."""
    z = np.asarray(z_um, dtype=np.float64)
    s = np.asarray(scores, dtype=np.float64)
    if z.ndim != 1 or s.ndim != 1:
        raise ValueError(f"z and scores must be 1-D, got shapes {z.shape} and {s.shape}")
    if z.size != s.size:
        raise ValueError(f"{z.size} z values but {s.size} scores: one score per z needed")
    if z.size < 3:
        raise ValueError(f"a focus curve needs at least 3 frames to locate a peak, got {z.size}")
    if not np.all(np.isfinite(z)):
        raise ValueError("z values must be finite (NaN or infinity found)")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores must be finite (NaN or infinity found)")
    order = np.argsort(z, kind="stable")
    z, s = z[order], s[order]
    if np.any(np.diff(z) <= 0):
        raise ValueError("z values must be distinct (a z appears twice)")
    return z, s


def score_noise(scores: np.ndarray) -> tuple[float, bool]:
    """Robust std of the score noise of a curve (n,), from its third differences.

    A third difference -s[i] + 3 s[i+1] - 3 s[i+2] + s[i+3] of white noise has
    variance 20 sigma**2, and it vanishes on any locally quadratic curve, so a
    smooth focus curve leaves it near zero except around a sharp peak. So the
    differences that touch the highest frame or its neighbours are left out,
    and the median of the rest ignores the few that the peak's shoulders still
    touch. Returns (sigma, clean): clean is False when fewer than two
    differences were away from the peak and all were used (an overestimate,
    fine for sigma, not for deciding that a curve is flat); (0.0, False) for
    fewer than 4 frames.
    """
    if scores.size < 4:
        return 0.0, False
    d3 = np.diff(scores, 3)
    first = np.arange(d3.size)  # difference i spans frames i .. i + 3
    best = int(np.argmax(scores))
    away = (first + 3 < best - 1) | (first > best + 1)
    clean = np.count_nonzero(away) >= 2
    if clean:
        d3 = d3[away]
    return _MAD_TO_SIGMA * float(np.median(np.abs(d3))) / math.sqrt(20.0), bool(clean)


def find_peak(
    z_um: np.ndarray, scores: np.ndarray, settings: PeakSettings | None = None
) -> PeakFit:
    """Best focus from a curve: z (n,) in um, scores (n,). See the module docstring."""
    settings = settings or PeakSettings()
    z, s = validate_curve(z_um, scores)
    top, span = abs(float(s.max())), float(s.max() - s.min())
    if settings.mode is PeakMode.VALLEY:
        # the valley is the peak of the curve turned upside down (lifted to stay
        # positive for the log fit: scores in [span, 2 span], nearly a plain parabola)
        s = float(s.max()) - s + span
    noise, clean = score_noise(s)
    if span <= settings.min_contrast * top or (clean and span <= settings.min_snr * noise):
        return PeakFit(None, None, frozenset({FocusFlag.FLAT}))
    return _find_max(z, s, noise, settings)


def _find_max(z: np.ndarray, s: np.ndarray, noise: float, settings: PeakSettings) -> PeakFit:
    span = float(s.max() - s.min())
    peaks, props = find_peaks(s, prominence=max(settings.multi_peak_share * span, 3.0 * noise))
    flags = {FocusFlag.MULTI_PEAK} if peaks.size > 1 else set()
    best = int(np.argmax(s))
    if best == 0:
        return PeakFit(float(z[0]), None, frozenset(flags | {FocusFlag.EDGE_LOW}))
    if best == z.size - 1:
        return PeakFit(float(z[-1]), None, frozenset(flags | {FocusFlag.EDGE_HIGH}))
    z0, sigma = _fit_vertex(z, s, best, noise, settings)
    if peaks.size > 1:
        # Either peak may be the specimen (the other dust, or a second layer): take the
        # variance of the choice between them, weighted by prominence, on top of the fit.
        weights = props["prominences"] / props["prominences"].sum()
        spread = float(np.sum(weights * (z[peaks] - z0) ** 2))
        sigma = math.sqrt(sigma**2 + spread)
    return PeakFit(z0, sigma, frozenset(flags))


def _fit_vertex(
    z: np.ndarray, s: np.ndarray, best: int, noise: float, settings: PeakSettings
) -> tuple[float, float]:
    """Vertex z (um) of a Gaussian (log-parabola) fit around interior frame `best`; its sigma."""
    floor = float(s.min())
    half = floor + 0.5 * (float(s[best]) - floor)
    reach = 1
    while (
        reach < 3
        and best - reach - 1 >= 0
        and best + reach + 1 < z.size
        and s[best - reach - 1] >= half
        and s[best + reach + 1] >= half
    ):
        reach += 1
    window = slice(best - reach, best + reach + 1)
    dz = z[window] - z[best]  # centred on the best frame: a well-conditioned fit
    values = s[window]
    use_log = bool(np.all(values > 0))
    y = np.log(values) if use_log else values
    # var(log s) = var(s) / s**2: weight each frame by s**2 / noise**2 (unit weights without log)
    weights = values**2 if use_log else np.ones_like(values)
    X = np.vander(dz, 3, increasing=True)  # columns 1, dz, dz**2
    XtW = X.T * weights
    normal_inv = np.linalg.inv(XtW @ X)
    _, b1, b2 = normal_inv @ (XtW @ y)
    step_um = float(np.median(np.diff(z)))
    if not b2 < 0:  # not a peak in the window (a plateau): the best frame, a step of doubt
        return float(z[best]), step_um
    z0 = float(z[best] - b1 / (2.0 * b2))
    # the vertex stays within the window: outside it the fit is extrapolation
    z0 = min(max(z0, float(z[window][0])), float(z[window][-1]))
    grad = np.array([0.0, -1.0 / (2.0 * b2), b1 / (2.0 * b2**2)])
    # weighted least squares with Var(y_i) = noise**2 / weights_i: Cov(b) = noise**2 (X'WX)^-1
    cov_b = noise**2 * normal_inv
    var_noise = float(grad @ cov_b @ grad) * settings.noise_scale**2
    # half width at half maximum of the fitted Gaussian: exp(b2 dz**2) = 1/2
    hwhm_steps = math.sqrt(math.log(2.0) / -b2) / step_um
    model_steps = min(
        math.hypot(settings.model_floor_steps, settings.model_sigma_steps / hwhm_steps),
        _QUANTISATION_STEPS,
    )
    return z0, math.sqrt(var_noise + (model_steps * step_um) ** 2)
