"""Best focus from a focus curve: a sub-step peak, an honest standard deviation, and flags.

The peak is refined below the z step by a Gaussian fitted around the best
frame: a weighted least-squares parabola in log(score), whose vertex is the
Gaussian's centre (exact for a Gaussian peak; Caruana's method with three
frames). Which frames: the three around the best, widened one frame each side
at a time (up to seven) for as long as the wider fit's vertex agrees with every
narrower one's within `PeakSettings.consistency_sigmas` of their noise
(Lepski's rule): on a clean, skewed peak the three-point fit has the least bias,
on a noisy one more frames average the noise.

Its standard deviation has six parts, added in quadrature:
- noise: the score noise (estimated from the curve itself, as the robust
  spread of its third differences: `score_noise`, or that estimate's upper confidence
  bound where `PeakSettings.own_noise_confidence` asks for it, `noise_bound`; never below
  the metric's known noise, `PeakSettings.min_relative_noise`) propagated through the
  weighted fit to the vertex z0 = -b1 / (2 b2) by the delta method;
- sampling: a floor of `model_floor_steps` z steps (a Gaussian fitted to a
  peak of another shape, sampled at an arbitrary phase);
- window: how far the chosen fit's vertex lies from that of the next window
  (one frame wider, or narrower where none is wider): a peak that is not a
  Gaussian, or one on a sloping background, moves with the window;
- asymmetry: a focus curve on a sloping background (dust on another plane adds
  contrast that grows towards it) is lopsided, and a Gaussian of variance
  w**2 on a log-background of slope c peaks c w**2 away from its centre. c is
  read from the curve as the odd part of log(score) about z0, over the frames
  mirrored within the curve: |c| w**2;
- top: on a broad peak drowned in noise, frames beyond the fit's reach may be
  the true top as likely as the best one (`_TopChances`): the spread of their
  z weighted by that chance;
- systematic: the metric's own offset from the plane a person picks
  (`PeakSettings.systematic_sigma_um`, learnt per metric from labelled curves).

Which peak (`_candidates`): real curves carry one-frame spikes and dips, second
peaks (dust, another layer), and backgrounds that rise towards an end. First,
frames that depart from their neighbours by more than a peak as wide as the
optics' depth of field (or, with a profile, a quarter of the metric's usual peak:
`curve_checks.narrowest_peak_sigma_um`) could make them are replaced by their
neighbours' prediction (`despike`). Then every local maximum with enough prominence is a
candidate, and so is an end frame that rises outwards (the peak may lie beyond
it). The rule: the weight of a candidate is its prominence squared, times the
request's prior density at it where there is a prior; the heaviest is chosen,
its share of the weights is its probability, and the next one is the runner-up.
That probability is scaled by the share of the top's chances near the chosen
frame (`_TopChances`: below one where noise leaves the top unlocated). The
choice is said with `multi_peak` (more than one candidate), `ambiguous`
(probability below `PeakSettings.ambiguous_below`) and the runner-up's z, never
folded into sigma: sigma is the chosen peak's own. An end chosen is an edge flag
pointing that way (no sigma).

Noise is judged (flat test, candidates, despike, the top's chances) by the
curve's own estimate where it is clean, else by the metric's known noise floor
alone: a short window cannot tell its noise from its peak's shape. In valley mode
the flat test also takes the estimate on the whole stack, whose frames outside the
window between the valley's maxima still measure the noise: a valley must stand
`min_snr` of it, as a peak must in max mode (a coarse first stack that misses a
narrow valley holds only noise-level wiggles between two far-out maxima).

Calibration (docs/focus.md): the constants were fitted on instrument-simulator
stacks of seeds 100-102 (`focustrack bench focus --seed 100` ...: all field
kinds, frame sizes, exposures and stack shapes) so that the z-scores (error /
sigma) of the metrics have a spread near one; the benchmark reports them on
seed 1. The two per-metric constants (`min_relative_noise`,
`systematic_sigma_um`) belong to a metric on a microscope and are 0 by default;
`focustrack focus calibrate` learns them from a user's labelled curves (a microscope
profile), `focustrack bench focus --real` on its fit fields. Shape checks for curves of
a microscope never seen (a phase-like valley, an oversampled curve's sigma floor, a
contrast judged by the curve's own noise, a top hidden under a far peak's foot or
resting on a window's end frame, a top broader than its window) are `curve_checks`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from focustrack_core.domain import MAX_ABS_Z_UM, FocusFlag, Prior
from focustrack_focus.curve_checks import (
    SHORT_STACK_FRAMES,
    between_maxima,
    broader_than_window,
    low_contrast_flat,
    narrow_at_end,
    narrowest_peak_sigma_um,
    oversampled_floor_um,
    phase_valley,
    shoulder,
    tied_with_end,
    uniform_sigma_um,
)
from focustrack_focus.despike import despike
from focustrack_focus.noise_bound import MAD_TO_SIGMA as MAD_TO_SIGMA  # its home: noise_bound
from focustrack_focus.noise_bound import bound_factor, score_noise


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
        (where the curve is long enough for a clean noise estimate, `score_noise`, or the
        metric's noise is known: `min_relative_noise`).
    multi_peak_share: a second local maximum at least this share of the curve's range
        high (prominence) makes the curve multi-peaked.
    max_reach: the fit uses at most this many frames each side of the best one.
    consistency_sigmas: a wider fit is kept while its vertex lies within this many noise
        sigmas of every narrower fit's vertex (module docstring).
    model_floor_steps: the sampling part of sigma, in z steps (module docstring).
    min_peak_sigma_um: the narrowest real peak (a Gaussian's std, um: about half the
        optics' depth of field); a one-frame excursion narrower than that is an outlier
        (`despike`).
    ambiguous_below: a chosen peak whose probability is below this is flagged ambiguous.
    end_rise_share: an end frame rising this share of the range above the frames inside
        it is a candidate peak beyond that end (`_candidates`).
    min_relative_noise: the metric's score noise on this microscope as a share of the
        curve's maximum, a floor under the curve's own estimate: a short window cannot
        tell its noise from its peak's shape, so without it a window of pure noise reads
        as a peak. It belongs to a metric on a microscope: 0 unless measured on full
        curves (`focustrack bench focus --real` measures it on its fit fields). 1 (noise as
        large as the maximum) turns off a metric found unusable on the microscope: no
        curve of non-negative scores then rises `min_snr` noise sigmas, so all are flat.
    systematic_sigma_um: the metric's own offset from the true focus (a std, um), added to
        every interior peak's sigma: a metric that weighs other spatial frequencies than
        the eye peaks a fraction of the depth of field away from the plane a person
        picks, by an amount no single curve shows. It belongs to a metric on a
        microscope: 0 unless learnt from labelled curves (`focustrack bench focus --real`
        learns it per metric on its fit fields; docs/focus.md); at most
        `MAX_SYSTEMATIC_SIGMA_UM`.
    curve_fwhm_um: the metric's usual peak width on this microscope (full width at half
        maximum, um; a microscope profile's, `focustrack focus calibrate`), or None. A peak
        read next to a window's end whose fit is far narrower rests on that one end frame
        (`curve_checks.narrow_at_end`), and a one-frame excursion narrower than a quarter
        of it is an outlier (`despike`). A top on the frame next to a window's end that
        stands less than `end_rise_share` of the range above that end frame rests on it
        too, with or without a profile (`curve_checks.tied_with_end`).
    broad_top_exempt_frames: windows of at most this many frames are exempt from the rule on
        a top broader than its window (`curve_checks.broader_than_window`): the scheduler's
        short stacks around a confident prediction see the top alone by design, which the
        service's own metrics read honestly there (the simulator's z-scores). 0 for a metric
        the service has no entry for (`unprofiled`).
    own_noise_confidence: where above 0, the noise that sigma and the top's chances take is
        the upper bound at this confidence of the curve's own noise estimate, which on a
        short window rests on a few differences and may fall far short of the noise
        (`noise_bound`; the flat test and the candidates keep the estimate). 0, the estimate
        itself, for the service's own metrics (fitted so on the simulator); 0.95 for a metric
        the service has no entry for (`unprofiled`).
    """

    mode: PeakMode = PeakMode.MAX
    min_contrast: float = 0.01
    min_snr: float = 10.0
    multi_peak_share: float = 0.25
    max_reach: int = 3
    consistency_sigmas: float = 2.0  # fitted on simulator seeds 100-102 (docs/focus.md)
    model_floor_steps: float = 0.02  # fitted on simulator seeds 100-102 (docs/focus.md)
    min_peak_sigma_um: float = 0.25  # half the 0.5 um depth of field of a 100x oil objective
    ambiguous_below: float = 0.75
    end_rise_share: float = 0.05
    min_relative_noise: float = 0.0
    systematic_sigma_um: float = 0.0
    curve_fwhm_um: float | None = None
    broad_top_exempt_frames: int = SHORT_STACK_FRAMES
    own_noise_confidence: float = 0.0

    def __post_init__(self) -> None:
        """ValueError naming the first setting out of its range: lab code builds these
        directly, and a value the peak maths cannot take (a negative sigma, a sigma whose
        square overflows) would fail, or silently mislead, every curve read with it."""
        if self.mode not in tuple(PeakMode):
            modes = ", ".join(repr(mode.value) for mode in PeakMode)
            raise ValueError(f"mode must be one of {modes}, got {self.mode!r:.40}")
        object.__setattr__(self, "mode", PeakMode(self.mode))  # "max" reads as PeakMode.MAX
        for name, low, high, above in (
            ("min_contrast", 0.0, 1.0, False),
            ("min_snr", 0.0, math.inf, False),
            ("multi_peak_share", 0.0, 1.0, True),
            ("consistency_sigmas", 0.0, math.inf, True),
            ("model_floor_steps", 0.0, math.inf, False),
            ("min_peak_sigma_um", 0.0, MAX_SYSTEMATIC_SIGMA_UM, False),
            ("ambiguous_below", 0.0, 1.0, False),
            ("end_rise_share", 0.0, 1.0, False),
            ("min_relative_noise", 0.0, 1.0, False),
            ("systematic_sigma_um", 0.0, MAX_SYSTEMATIC_SIGMA_UM, False),
            ("own_noise_confidence", 0.0, 1.0, False),
        ):
            check_number(name, getattr(self, name), low, high, above=above)
        if self.curve_fwhm_um is not None:
            check_number("curve_fwhm_um", self.curve_fwhm_um, 0.0, math.inf, above=True)
        for name, least in (("max_reach", 1), ("broad_top_exempt_frames", 0)):
            count = getattr(self, name)
            if not (isinstance(count, int) and not isinstance(count, bool) and count >= least):
                raise ValueError(f"{name} must be a whole number >= {least}, got {count!r}")


@dataclass(frozen=True)
class PeakFit:
    """The focus read from a curve, in um. z_um and sigma_um are None where there is none.

    For an edge peak z_um is the edge frame's z and sigma_um None: the focus is
    beyond the range, in the direction the flag says. With more than one peak,
    runner_up_z_um is the z of the next most likely one (an end frame when that
    peak lies beyond the range) and chosen_probability the chosen peak's share of
    the weights (`_candidates`) times the share of the top's chances near it
    (`_TopChances`); on a single, clearly located peak they are None and 1.0.
    """

    z_um: float | None
    sigma_um: float | None
    flags: frozenset[FocusFlag]
    runner_up_z_um: float | None = None
    chosen_probability: float | None = None

    @property
    def is_observation(self) -> bool:
        return self.sigma_um is not None

    def posterior(self, prior: Prior) -> tuple[float, float] | None:
        """(z, sigma) in um of the prior updated with this measurement (the product of two
        Gaussians); None where this fit is no measurement."""
        if self.z_um is None or self.sigma_um is None:
            return None
        precision = 1.0 / prior.sigma_um**2 + 1.0 / self.sigma_um**2
        z = (prior.z_um / prior.sigma_um**2 + self.z_um / self.sigma_um**2) / precision
        return z, math.sqrt(1.0 / precision)


def check_number(name: str, value: object, low: float, high: float, *, above: bool) -> None:
    """ValueError naming `name` unless `value` is a number (a boolean is not one) within
    [low, high], or (low, high] when `above`, and finite (NaN fails the comparisons)."""
    in_range = (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and (low < value if above else low <= value)
        and value <= high
        and -math.inf < value < math.inf
    )
    if not in_range:
        if high == math.inf:
            wanted = f"a finite number {'>' if above else '>='} {low:g}"
        else:
            wanted = f"a number in {'(' if above else '['}{low:g}, {high:g}]"
        raise ValueError(f"{name} must be {wanted}, got {value!r:.40}")


#: Fewest frames (or points) of a curve a peak is located on: a top and a frame either side.
MIN_CURVE_FRAMES = 3
#: Largest systematic sigma of a metric, um (`PeakSettings.systematic_sigma_um`): a
#: millimetre, thousands of times the depth of field of the lowest-power objective; a
#: metric offset further from a person's focus is no focus metric, and a value beyond
#: it is a unit gone wrong (its square, added to every sigma's, overflows near 1e154).
MAX_SYSTEMATIC_SIGMA_UM = 1000.0
#: Largest |score|: the slide's curve model (`curve_model`) squares scores as they come, and
#: a square beyond a float's range is NaN (`find_peak` reads them scaled to 1).
MAX_ABS_SCORE = 1e150
#: Smallest z step of a curve, um: a picometre, a thousandth of a piezo stage's nanometre
#: step. A finer one is a unit gone wrong, and its powers in the fit (dz**4) underflow.
MIN_Z_STEP_UM = 1e-6
#: How far a step between two z of at most MAX_ABS_Z_UM may be rounded (an ulp of each):
#: a step of MIN_Z_STEP_UM passes however its z were rounded (1e6 - 1e-6 and 1e6 are
#: 9.99891e-07 apart in floats).
_Z_STEP_ROUNDING_UM = 2.0 * float(np.spacing(MAX_ABS_Z_UM))


def validate_curve(z_um: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check a curve and sort it by z; ValueError saying what is wrong. Shapes (n,), n >=
    MIN_CURVE_FRAMES."""
    z = np.asarray(z_um, dtype=np.float64)
    s = np.asarray(scores, dtype=np.float64)
    if z.ndim != 1 or s.ndim != 1:
        raise ValueError(f"z and scores must be 1-D, got shapes {z.shape} and {s.shape}")
    if z.size != s.size:
        raise ValueError(f"{z.size} z values but {s.size} scores: one score per z needed")
    if z.size < MIN_CURVE_FRAMES:
        raise ValueError(
            f"a focus curve needs at least {MIN_CURVE_FRAMES} frames to locate a peak, got {z.size}"
        )
    if not np.all(np.abs(z) <= MAX_ABS_Z_UM):
        raise ValueError(f"z values must be finite and within +/-{MAX_ABS_Z_UM:g} um")
    if not np.all(np.abs(s) <= MAX_ABS_SCORE):
        raise ValueError(f"scores must be finite and within +/-{MAX_ABS_SCORE:g}")
    order = np.argsort(z, kind="stable")
    z, s = z[order], s[order]
    steps_um = np.diff(z)
    too_fine = steps_um < MIN_Z_STEP_UM - _Z_STEP_ROUNDING_UM
    if np.any(too_fine):
        at = int(np.argmax(too_fine))
        raise ValueError(
            f"z values must be distinct and at least {MIN_Z_STEP_UM:g} um apart: "
            f"{z[at]} and {z[at + 1]} um are {steps_um[at]:.3g} um apart"
        )
    return z, s


def find_peak(
    z_um: np.ndarray,
    scores: np.ndarray,
    settings: PeakSettings | None = None,
    prior: Prior | None = None,
) -> PeakFit:
    """Best focus from a curve: z (n,) in um, scores (n,). See the module docstring.

    `prior`: the estimator's belief about the focus before this stack (um); it
    weighs the choice between peaks, not the fit of the chosen one.
    """
    settings = settings or PeakSettings()
    z, s = validate_curve(z_um, scores)
    stack_noise, stack_clean = 0.0, False
    if settings.mode is PeakMode.VALLEY:
        # the stack's noise, estimated on all its frames: the window between the valley's
        # maxima is too short for a clean estimate of its own (a coarse stack's 5-6 frames
        # with the valley in the middle leave no difference away from it)
        stack_noise, stack_clean = score_noise(s)
        z, s = between_maxima(z, s)
    # read on a scale of 1, the same for any scale of scores: scores of 1e-160 squared in
    # the fit's weights underflow to a singular matrix
    scale = float(np.abs(s).max()) or 1.0
    s = s / scale
    top, span = abs(float(s.max())), float(s.max() - s.min())
    if settings.mode is PeakMode.VALLEY:
        # the valley is the peak of the curve turned upside down (lifted to stay
        # positive for the log fit: scores in [span, 2 span], nearly a plain parabola)
        s = float(s.max()) - s + span
    own, clean = score_noise(s)
    # a noise estimate that is not clean took in the peak's own shape: too large to judge
    # which bumps are noise, so then only the metric's known noise floor judges (and
    # where there is none, the prominence share alone decides: `_candidates`)
    floor = settings.min_relative_noise * top
    judged_noise = max(own if clean else 0.0, floor)
    noise = max(own, floor)
    # a valley must stand `min_snr` of the stack's noise, as a peak must in max mode: the
    # frames cropped away measure it still (a curve of noise dips somewhere between two
    # of its maxima)
    flat_noise = max(judged_noise, stack_noise / scale if stack_clean else 0.0)
    if _flat(s, top, noise, flat_noise, clean, settings):
        return PeakFit(None, None, frozenset({FocusFlag.FLAT}))
    # sigma and the top's chances: the own estimate's upper bound where asked (`noise_bound`)
    bound = own * bound_factor(s.size, int(np.argmax(s)), settings.own_noise_confidence)
    read_noise = _Noise(max(bound, floor), judged_noise, max(bound if clean else 0.0, floor))
    s = despike(
        z,
        s,
        judged_noise,
        narrowest_peak_sigma_um(settings.min_peak_sigma_um, settings.curve_fwhm_um),
    )
    # a curve whose contrast was a one-frame outlier is flat (a spike on a zero baseline
    # left zeros, read as an edge); where the outlier was the maximum, the top is the rest's
    if settings.mode is PeakMode.MAX:
        top = abs(float(s.max()))
    if _flat(s, top, noise, flat_noise, clean, settings):
        return PeakFit(None, None, frozenset({FocusFlag.FLAT}))
    fit = _read_peaks(z, s, read_noise, settings, prior)
    valley_z = phase_valley(z, s) if settings.mode is PeakMode.MAX else None
    if valley_z is None:
        return fit
    # an unstained specimen's focus is this minimum: never a confident maximum
    flags = fit.flags | {FocusFlag.VALLEY, FocusFlag.AMBIGUOUS}
    probability = min(fit.chosen_probability or 1.0, 0.5)
    return replace(
        fit, flags=frozenset(flags), runner_up_z_um=valley_z, chosen_probability=probability
    )


#: A range of scores read on a scale of 1 (`find_peak`) that is float round-off, not
#: contrast: what is left of a curve of one value once `despike` has replaced a frame
#: with its neighbours' weighted sum (about 1e-16, where there is no noise to judge by).
_ROUND_OFF = 1e-12


def _flat(
    s: np.ndarray,
    top: float,
    noise: float,
    judged_noise: float,
    clean: bool,
    settings: PeakSettings,
) -> bool:
    """Whether the curve `s` (n,) as read holds no peak (`find_peak`'s noise estimates): its
    contrast too low for its maximum `top` (`curve_checks.low_contrast_flat`), or its range
    within `min_snr` sigmas of the noise where that is judged, or within float round-off."""
    contrast_flat = low_contrast_flat(s, top, noise, clean, settings.min_contrast, settings.min_snr)
    span = float(s.max() - s.min())
    return contrast_flat or span <= max(settings.min_snr * judged_noise, _ROUND_OFF)


@dataclass(frozen=True)
class _Candidate:
    """A peak of the curve: frame index, prominence (score units), weight in the choice."""

    index: int
    prominence: float
    weight: float


def _candidates(
    z: np.ndarray, s: np.ndarray, judged_noise: float, settings: PeakSettings, prior: Prior | None
) -> list[_Candidate]:
    """The curve's peaks, an end that rises outwards included (the peak may lie beyond it),
    most likely first. The rule: weight = prominence ** 2, times, with a prior, the
    prior's density at the peak (its sigma widened by one z step).

    An interior peak counts from `multi_peak_share` of the range; an end from
    `end_rise_share` (a window far from focus sees only the peak's faint tail rising
    towards it, and a background rising more at the other end must not hide it).
    Both need 3 noise sigmas where the noise is judged (`find_peak`).
    """
    span = float(s.max() - s.min())
    # padded with the curve's minimum: an end that rises outwards becomes a peak, and the
    # prominence of every peak is still measured from the curve's own frames
    padded = np.concatenate([[s.min()], s, [s.min()]])
    floor = min(settings.multi_peak_share, settings.end_rise_share) * span
    from scipy.signal import find_peaks  # imported on first use: 1.5 s, not at start-up

    found, props = find_peaks(padded, prominence=max(floor, 3.0 * judged_noise))
    indices, prominences = found - 1, props["prominences"]
    is_end = (indices == 0) | (indices == s.size - 1)
    share = np.where(is_end, settings.end_rise_share, settings.multi_peak_share)
    keep = prominences >= np.maximum(share * span, 3.0 * judged_noise)
    indices, prominences = indices[keep], prominences[keep]
    best = int(np.argmax(s))
    if best not in indices:  # a plateau's maximum: find_peaks sees no peak; keep the best frame
        indices, prominences = np.append(indices, best), np.append(prominences, span)
    weights = prominences**2
    if prior is not None:
        step_um = float(np.median(np.diff(z)))
        spread_um2 = prior.sigma_um**2 + step_um**2
        weights = weights * np.exp(-0.5 * (z[indices] - prior.z_um) ** 2 / spread_um2)
        if not np.any(weights > 0):  # every peak far outside the prior: prominence alone
            weights = prominences**2
    order = np.argsort(-weights, kind="stable")
    return [
        _Candidate(int(indices[i]), float(prominences[i]), float(weights[i] / weights.sum()))
        for i in order
    ]


@dataclass(frozen=True)
class _Noise:
    """The score noise each part of a reading takes (`find_peak`), each at least the metric's
    known floor: the fit's sigma (`fit`: the curve's own estimate), the candidates and the
    shoulder test (`judged`: the own estimate where it is clean, else none) and the top's
    chances (`top`: as `judged`). Where `PeakSettings.own_noise_confidence` asks for it,
    `fit` and `top` take the own estimate's upper bound instead (`noise_bound`)."""

    fit: float
    judged: float
    top: float


def _read_peaks(
    z: np.ndarray, s: np.ndarray, noise: _Noise, settings: PeakSettings, prior: Prior | None
) -> PeakFit:
    candidates = _candidates(z, s, noise.judged, settings, prior)
    chosen = candidates[0]
    flags: set[FocusFlag] = set()
    runner_up_z = None
    if len(candidates) > 1:
        flags.add(FocusFlag.MULTI_PEAK)
        runner_up_z = float(z[candidates[1].index])
    others = [c.index for c in candidates[1:]]
    top = _TopChances.of(s, chosen.index, others, noise.top, settings.max_reach)
    probability = chosen.weight * top.located
    if probability < settings.ambiguous_below:
        flags.add(FocusFlag.AMBIGUOUS)
    if chosen.index in (0, z.size - 1):
        edge = FocusFlag.EDGE_LOW if chosen.index == 0 else FocusFlag.EDGE_HIGH
        hidden = shoulder(s, chosen.index > 0, noise.judged) if len(candidates) == 1 else None
        if hidden is not None:  # a top of its own under a far peak's foot: no certainty
            flags |= {FocusFlag.MULTI_PEAK, FocusFlag.AMBIGUOUS}
            runner_up_z, probability = float(z[hidden]), min(probability, 0.5)
        return PeakFit(
            float(z[chosen.index]), None, frozenset(flags | {edge}), runner_up_z, probability
        )
    z0, sigma, width_var_um2 = _fit_vertex(z, s, chosen.index, noise.fit, settings)
    sigma = math.hypot(sigma, top.spread_um(z, z0))
    span_um = float(z[-1] - z[0])
    if broader_than_window(width_var_um2, span_um, z.size, settings.broad_top_exempt_frames):
        # the window sees a gentle curvature, no top of its own: anywhere in it
        flags.add(FocusFlag.AMBIGUOUS)
        sigma = max(sigma, uniform_sigma_um(span_um))
        probability = min(probability, 0.5)
    end = 0 if chosen.index == 1 else z.size - 1 if chosen.index == z.size - 2 else None
    if end is not None and _rests_on_end(z, s, chosen.index, end, noise.fit, settings):
        # the top rests on the end frame alone: were it a one-frame dip, the focus
        # would lie beyond that end
        flags |= {FocusFlag.MULTI_PEAK, FocusFlag.AMBIGUOUS}
        runner_up_z, probability = float(z[end]), min(probability, 0.5)
    return PeakFit(z0, sigma, frozenset(flags), runner_up_z, probability)


def _rests_on_end(
    z: np.ndarray, s: np.ndarray, top: int, end: int, noise: float, settings: PeakSettings
) -> bool:
    """Whether the top at frame `top`, next to the window's end frame `end`, has that frame
    alone for its outer flank and too little of it to tell a top from a one-frame dip
    (`curve_checks.narrow_at_end`, `curve_checks.tied_with_end`)."""
    if tied_with_end(s, top, end, settings.end_rise_share):
        return True
    if settings.curve_fwhm_um is None:
        return False
    top_fit = _fit_window(z, s, top, 1, noise)
    return top_fit is not None and narrow_at_end(top_fit.width_var_um2, settings.curve_fwhm_um)


@dataclass(frozen=True)
class _TopChances:
    """How well the noise lets the chosen peak's top be located: the chance (n,) that each
    frame of its part of the curve is the true top, and the share of it near the chosen
    frame.

    A frame lower than the chosen top by d is higher than it in truth with chance
    Phi(-d / (sqrt(2) noise)) (both frames carry noise). Near the top of a broad peak
    drowned in noise (a metric blind to this specimen: a curve of noise on a faint
    bump), frames far from the chosen one are as likely the top as it is: the fit
    around it, which only sees the noise of its own frames, says nothing of that.
    Frames within the fit's reach are the fit's own business (its noise part); frames
    nearer another candidate belong to that peak, whose share the choice already gives
    (`_candidates`): the doubt between peaks stays out of sigma.
    """

    chances: np.ndarray
    far: np.ndarray
    located: float

    @classmethod
    def of(
        cls, s: np.ndarray, chosen: int, others: list[int], judged_noise: float, reach: int
    ) -> _TopChances:
        frames = np.arange(s.size)
        distance = np.abs(frames - chosen)
        far = distance > reach
        if judged_noise <= 0.0:  # no noise to judge by (`find_peak`)
            return cls(np.zeros(s.size), far, 1.0)
        drop = np.maximum(s[chosen] - s, 0.0) / (math.sqrt(2.0) * judged_noise)
        from scipy import special  # imported on first use, not at start-up

        chances = 0.5 * special.erfc(drop / math.sqrt(2.0))
        for other in others:
            chances[np.abs(frames - other) < distance] = 0.0
        return cls(chances, far, float(chances[~far].sum() / chances.sum()))

    def spread_um(self, z: np.ndarray, z0: float) -> float:
        """The std (um) about z0 that the far frames' chances of being the top add."""
        total = self.chances.sum()
        if total <= 0.0:
            return 0.0
        far = self.far
        return math.sqrt(float(np.sum(self.chances[far] * (z[far] - z0) ** 2) / total))


@dataclass(frozen=True)
class _Vertex:
    """A log-parabola fit around the best frame: vertex z (um), its noise std (um) and the
    variance (um**2) of the fitted Gaussian (0 for a fit of the scores themselves)."""

    z_um: float
    noise_sigma_um: float
    width_var_um2: float


def _fit_window(
    z: np.ndarray, s: np.ndarray, best: int, reach: int, noise: float
) -> _Vertex | None:
    """Fit frames best - reach .. best + reach; None when they hold no peak (b2 >= 0)."""
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
    if not b2 < 0:
        return None
    # the vertex stays within the window: outside it the fit is extrapolation
    z0 = min(max(float(z[best] - b1 / (2.0 * b2)), float(z[window][0])), float(z[window][-1]))
    grad = np.array([0.0, -1.0 / (2.0 * b2), b1 / (2.0 * b2**2)])
    # weighted least squares with Var(y_i) = noise**2 / weights_i: Cov(b) = noise**2 (X'WX)^-1
    noise_var = float(grad @ (noise**2 * normal_inv) @ grad)
    # log(Gaussian) = -dz**2 / (2 w**2) + ...: w**2 = -1 / (2 b2) (no width without the log)
    return _Vertex(z0, math.sqrt(noise_var), -1.0 / (2.0 * b2) if use_log else 0.0)


def _fit_vertex(
    z: np.ndarray, s: np.ndarray, best: int, noise: float, settings: PeakSettings
) -> tuple[float, float, float]:
    """Vertex z (um) of the Gaussian fit around interior frame `best`, its sigma (um) and the
    fitted Gaussian's variance (um**2; 0 where the fit is not of log-scores)."""
    step_um = float(np.median(np.diff(z)))
    fits: list[_Vertex] = []
    for reach in range(1, min(best, z.size - 1 - best, settings.max_reach) + 1):
        fit = _fit_window(z, s, best, reach, noise)
        if fit is None:
            break
        fits.append(fit)
    if not fits:  # not a peak even over three frames (a plateau): the best frame, a step of doubt
        return float(z[best]), math.hypot(step_um, settings.systematic_sigma_um), 0.0
    chosen, limit = 0, settings.consistency_sigmas
    for wider in range(1, len(fits)):
        if any(abs(fits[wider].z_um - f.z_um) > limit * f.noise_sigma_um for f in fits[:wider]):
            break
        chosen = wider
    fit = fits[chosen]
    neighbour = fits[chosen + 1] if chosen + 1 < len(fits) else fits[chosen - 1] if chosen else None
    window_um = abs(neighbour.z_um - fit.z_um) if neighbour else 0.0
    asymmetry_um = _log_slope_about(z, s, fit.z_um) * fit.width_var_um2
    variance = (
        fit.noise_sigma_um**2
        + peak_floor_sigma_um(step_um, settings) ** 2
        + window_um**2
        + asymmetry_um**2
    )
    sigma = max(math.sqrt(variance), oversampled_floor_um(step_um, settings.min_peak_sigma_um))
    return fit.z_um, sigma, fit.width_var_um2


def peak_floor_sigma_um(step_um: float, settings: PeakSettings) -> float:
    """The part of a peak's sigma (um) that no curve's noise shows, for frames `step_um`
    apart: the sampling floor (`model_floor_steps` steps) and the metric's systematic
    offset (module docstring)."""
    return math.hypot(settings.model_floor_steps * step_um, settings.systematic_sigma_um)


def _log_slope_about(z: np.ndarray, s: np.ndarray, z0: float) -> float:
    """|c| (1/um): the odd part of log(score) about z0, fitted as c d over mirrored offsets d.

    Uses the frames whose mirror image about z0 lies inside the curve (scores
    interpolated there); 0 where there are none or a score is not positive.
    """
    if not np.all(s > 0):
        return 0.0
    log_s = np.log(s)
    offsets = np.abs(z - z0)
    offsets = offsets[(offsets > 0) & (offsets <= min(z0 - z[0], z[-1] - z0))]
    if offsets.size == 0:
        return 0.0
    odd = (np.interp(z0 + offsets, z, log_s) - np.interp(z0 - offsets, z, log_s)) / 2.0
    return abs(float(np.sum(odd * offsets) / np.sum(offsets**2)))
