"""Checks of a focus curve's shape that `peak.find_peak` applies besides its fit.

- A phase-like valley (`phase_valley`): an unstained specimen in brightfield loses its
  contrast in focus and reverses it across focus, so its curve falls to a sharp minimum
  at focus between two maxima, below the contrast of the far-out frames. A maximum-
  contrast reading of it lands one or two depths of field away; the curve is flagged
  `valley` (with `ambiguous`), and the minimum's z is given as the runner-up.
- The frames between a valley's two maxima (`twin_maxima`): read in valley mode, a curve
  far wider than the defocus contrast (a first tile's coarse search) falls again beyond
  its two maxima, and turned upside down those far-out frames rise towards the ends like
  a peak beyond the window. The valley mode reads the frames from one maximum to the
  other, where the focus lies; where it sees no two maxima (thick cells lose their
  contrast fast on one side of focus, and a coarse step can hide the dip), the frames
  near the strongest contrast (`VALLEY_REACH_UM`).
- An oversampled curve's sigma floor (`oversampled_floor_um`): where frames are far
  closer than the optics' depth of field, the fit's sub-step precision (a fraction of a
  tiny step) says nothing of how far the metric's own peak lies from the true focus,
  which is a matter of the optics, not of the step: sigma is kept above a share of the
  depth of field (`PeakSettings.min_peak_sigma_um` is half of it).
- A hidden top on the way to an edge (`shoulder`): a window near focus may see the foot of
  a sharper peak beyond its end (debris on another plane) rise over its own top, which
  then shows only as a shoulder, where the rise slows and speeds up again. The edge
  flag then names the far peak's side with no certainty: the shoulder is the runner-up.
- A top resting on a window's end frame (`narrow_at_end`, `tied_with_end`): a peak read on
  the frame next to a window's end has one frame for its outer flank, and an end frame is
  the one frame `despike.despike` cannot check (it has neighbours on one side only). Where
  the top's fit is far narrower than the metric's peaks on this microscope (a profile's
  `curve_fwhm_um`), or where the top stands above that end frame by less than the share
  of the range that makes a rising end frame a candidate peak (`end_rise_share`: a near
  tie), that end frame may be a one-frame dip and the curve falling from beyond the end:
  ambiguous, the end the runner-up. Windows of fewer than 5 frames are the lean scan's
  short stacks, which the slide's curve model reads (`curve_model`).
- A one-frame excursion narrower than the metric's peaks (`narrowest_peak_sigma_um`):
  where a profile gives the metric's usual peak width on this microscope, a frame that
  departs from its neighbours more than a peak of a quarter of that width could make it
  is an outlier (`despike.despike`), not only one beyond the optics' narrowest peak.
- A contrast too low to call, measured against the curve's own noise (`low_contrast_flat`):
  a share of the maximum is a stand-in for the noise where the curve is too short to
  measure it; a long clean curve whose peak stands many of its own noise spreads above
  both end frames is no flat curve, however small its contrast (a 5x objective on pale
  tissue). A pale curve that does not rise so far above its ends is flat still: a camera
  whose brightness alone changes with z (Micro-Manager's demo camera, a lamp warming up)
  draws a clean, slow wander with no focus in it.
- A top broader than its window (`broader_than_window`): where the Gaussian fitted to the
  chosen top has a std wider than the whole window, the window sees a gentle curvature
  and no top of its own (a metric blind to this specimen: a faint bump under noise). The
  fit's vertex then rests on the frames' noise and on how the metric's broad response
  leans, not on the focus: the reading is ambiguous, and its sigma at least that of a
  focus equally likely anywhere in the window (`uniform_sigma_um`). It needs no profile
  and no constant of a microscope: a width compared with the window that measured it.
  Stacks of at most 5 frames are exempt: the scheduler places them around a confident
  prediction to see the top alone (on the simulator, every top broader than its window
  was such a stack).
"""

from __future__ import annotations

import numpy as np

from focustrack_focus.noise_bound import score_noise

#: A valley: both maxima rise at least this share of the range above the minimum, and
#: both end frames at least `VALLEY_BELOW_ENDS` of it (the far-out frames keep contrast).
VALLEY_RISE_SHARE = 0.5
VALLEY_BELOW_ENDS = 0.25
#: ... and it is narrow: its width at half depth is at most this share of the distance
#: between the two maxima (two peaks on a background leave a broad trough between them).
VALLEY_WIDTH_SHARE = 0.5
#: A valley to read between its maxima (`twin_maxima`) sinks half the curve's range, or,
#: on a curve long enough to measure its own noise, this many of its noise sigmas: far out
#: of focus the contrast fades, so the range of a first tile's coarse stack is mostly the
#: fading, not the valley (a 25 % dip on the simulator's red cells, at 4 um steps).
VALLEY_DIP_NOISES = 5.0
#: Without two maxima, a valley is read within this distance (um) of the curve's highest
#: frame: a phase object's defocus contrast is strongest a few um from its focus (4-8 um
#: on the simulator's red cells) and fades beyond, so frames far out, the faintest of all,
#: are no focus. Thick cells in culture lose their contrast fast on one side of focus, and
#: at 4 um steps one first stack showed no dip at all; read whole, its faded end (+28 um)
#: was the focus.
VALLEY_REACH_UM = 8.0
#: A curve is oversampled where its step is below this share of `min_peak_sigma_um` (an
#: eighth of the depth of field: 0.06 um for a 100x oil objective, whose 0.25-0.5 um steps
#: keep the step-based parts of sigma) ...
OVERSAMPLED_STEP_SHARE = 0.25
#: ... and then its sigma is at least this share of `min_peak_sigma_um` (a quarter of the
#: depth of field).
OVERSAMPLED_FLOOR_SHARE = 0.5


def phase_valley(z: np.ndarray, s: np.ndarray) -> float | None:
    """The z (um) of a phase-like valley of the curve (module docstring), or None.

    z (n,) sorted, s (n,) scores. The minimum must be interior, the highest frame on each
    side of it must rise `VALLEY_RISE_SHARE` of the range above it, both end frames
    `VALLEY_BELOW_ENDS`, and its width at half the lower side's depth must be at most
    `VALLEY_WIDTH_SHARE` of the distance between the two maxima."""
    low = int(np.argmin(s))
    if low in (0, s.size - 1):
        return None
    span = float(s.max() - s.min())
    if span <= 0:
        return None
    left_top = int(np.argmax(s[:low]))
    right_top = low + 1 + int(np.argmax(s[low + 1 :]))
    rise = min(s[left_top], s[right_top]) - s[low]
    if rise < VALLEY_RISE_SHARE * span or min(s[0], s[-1]) - s[low] < VALLEY_BELOW_ENDS * span:
        return None
    half = s[low] + rise / 2.0
    above = np.flatnonzero(s >= half)
    left_edge, right_edge = above[above < low][-1], above[above > low][0]
    if z[right_edge] - z[left_edge] > VALLEY_WIDTH_SHARE * (z[right_top] - z[left_top]):
        return None
    return float(z[low])


def twin_maxima(s: np.ndarray) -> tuple[int, int] | None:
    """The first and last index of the frames from one maximum of a valley to the other, or
    None where the curve s (n,) has no such valley (module docstring).

    One maximum is the highest frame; the other is the frame, on either side of it, over
    which the curve dipped deepest between the two (the depth measured below the lower of
    them). A valley must sink at least `VALLEY_RISE_SHARE` of the curve's range, or, on a
    curve long enough for a clean estimate of its own noise (`noise_bound.score_noise`),
    `VALLEY_DIP_NOISES` of its noise sigmas: a short stack on one side of the focus has
    none, and one about it, the V alone, is read whole (its end frames are its maxima)."""
    top = int(np.argmax(s))
    deepest, other = 0.0, top
    for step in (1, -1):  # outward from the top on each side
        side = s[top::step]
        # at each frame: how far the curve dipped on its way there, below the lower end
        depth = np.minimum(side[0], side) - np.minimum.accumulate(side)
        far = int(np.argmax(depth))
        if depth[far] > deepest:
            deepest, other = float(depth[far]), top + step * far
    least = VALLEY_RISE_SHARE * float(s.max() - s.min())
    noise, clean = score_noise(s)
    if clean:
        least = min(least, VALLEY_DIP_NOISES * noise)
    if deepest <= 0.0 or deepest < least:
        return None
    return min(top, other), max(top, other)


def between_maxima(z_um: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames of a curve, z (n,) ascending and s (n,), from one maximum of its valley to
    the other (`twin_maxima`); where it has no valley, those within `VALLEY_REACH_UM` (and
    at least two steps) of its highest frame."""
    if (between := twin_maxima(s)) is None:
        step_um = float(np.median(np.diff(z_um))) if z_um.size > 1 else 0.0
        reach_um = max(VALLEY_REACH_UM, 2.0 * step_um)
        near = np.abs(z_um - z_um[int(np.argmax(s))]) <= reach_um
        return z_um[near], s[near]
    first, last = between
    return z_um[first : last + 1], s[first : last + 1]


def oversampled_floor_um(step_um: float, min_peak_sigma_um: float) -> float:
    """The sigma floor (um) of a peak read from frames `step_um` apart by optics whose
    narrowest peak has std `min_peak_sigma_um`: OVERSAMPLED_FLOOR_SHARE of it where the
    step is below OVERSAMPLED_STEP_SHARE of it, else 0 (module docstring)."""
    if step_um >= OVERSAMPLED_STEP_SHARE * min_peak_sigma_um:
        return 0.0
    return OVERSAMPLED_FLOOR_SHARE * min_peak_sigma_um


#: A shoulder: the rise slows to at most this share of its steepest slope before it ...
SHOULDER_SLOW_SHARE = 0.35
#: ... and then speeds up again to at least this many times the slow slope.
SHOULDER_SPEED_UP = 3.0


def shoulder(s: np.ndarray, rising_to_high: bool, noise: float) -> int | None:
    """The frame of a shoulder on a curve (n,) that rises toward one end (`rising_to_high`:
    the high-z end), or None (module docstring): an interior frame where the step to the
    next frame is at most SHOULDER_SLOW_SHARE of an earlier, steeper step of the rise and
    SHOULDER_SPEED_UP times smaller than a later one, every step compared beyond 3 noise
    sigmas of the difference of two frames."""
    rise = np.diff(s if rising_to_high else s[::-1])
    margin = 3.0 * np.sqrt(2.0) * noise
    for i in range(1, rise.size - 1):
        earlier, later = rise[:i].max(), rise[i + 1 :].max()
        slow = max(rise[i], 0.0)
        if (
            earlier > margin
            and slow <= SHOULDER_SLOW_SHARE * earlier
            and later >= SHOULDER_SPEED_UP * slow + margin
        ):
            return i if rising_to_high else s.size - 1 - i
    return None


#: A top's fit narrower than this share of the metric's usual peak (Gaussian stds) is
#: suspect where it rests on an end frame.
NARROW_SHARE = 0.5
#: A Gaussian's full width at half maximum over its std.
FWHM_PER_SIGMA = 2.0 * float(np.sqrt(2.0 * np.log(2.0)))


def narrow_at_end(width_var_um2: float, curve_fwhm_um: float) -> bool:
    """Whether a top fitted as a Gaussian of variance `width_var_um2` (um**2; 0: not a
    log fit) is narrower than NARROW_SHARE of the metric's usual peak, `curve_fwhm_um` wide
    at half maximum (module docstring)."""
    if width_var_um2 <= 0.0:
        return False
    return float(np.sqrt(width_var_um2)) < NARROW_SHARE * curve_fwhm_um / FWHM_PER_SIGMA


def low_contrast_flat(
    s: np.ndarray, top: float, noise: float, clean: bool, min_contrast: float, min_snr: float
) -> bool:
    """Whether the curve `s` (n,) as read (its focus a maximum), whose scores' maximum is
    `top`, is too low in contrast to hold a peak: its range below `min_contrast` of `top`,
    unless its own noise estimate is clean and its maximum stands `min_snr` of those noise
    spreads above both end frames (a peak inside the stack; module docstring)."""
    if float(s.max() - s.min()) > min_contrast * top:
        return False
    rise_from_ends = float(s.max() - max(s[0], s[-1]))
    return not (clean and rise_from_ends > min_snr * noise)


#: A one-frame excursion narrower than this share of the metric's usual peak (Gaussian
#: stds) is an outlier where that peak's width is known (`despike.despike`).
SPIKE_SHARE = 0.25


def narrowest_peak_sigma_um(min_peak_sigma_um: float, curve_fwhm_um: float | None) -> float:
    """The std (um) of the narrowest peak a curve may hold: the optics' (`min_peak_sigma_um`)
    or, where the metric's usual peak width on this microscope is known (a profile's
    `curve_fwhm_um`), SPIKE_SHARE of that peak's std if wider (module docstring)."""
    if curve_fwhm_um is None:
        return min_peak_sigma_um
    return max(min_peak_sigma_um, SPIKE_SHARE * curve_fwhm_um / FWHM_PER_SIGMA)


#: Windows of fewer frames are the lean scan's short stacks (`curve_model` reads them).
TIED_MIN_FRAMES = 5


def tied_with_end(s: np.ndarray, top: int, end: int, share: float) -> bool:
    """Whether the top at frame `top` of a window `s` (n,) next to its end frame `end` stands
    less than `share` of the window's range above that end frame (module docstring); never
    for windows of fewer than TIED_MIN_FRAMES frames."""
    if s.size < TIED_MIN_FRAMES:
        return False
    return float(s[top] - s[end]) < share * float(s.max() - s.min())


#: A top whose fitted Gaussian's std is wider than this share of the window's span ...
BROAD_TOP_SHARE = 1.0
#: ... in a window of more frames than this (a shorter one is a stack placed around a
#: confident prediction, which sees only the top by design).
SHORT_STACK_FRAMES = 5


def broader_than_window(
    width_var_um2: float, span_um: float, n_frames: int, exempt_frames: int = SHORT_STACK_FRAMES
) -> bool:
    """Whether a top fitted as a Gaussian of variance `width_var_um2` (um**2; 0: not a log
    fit) is broader than BROAD_TOP_SHARE of the span `span_um` of a window of `n_frames`
    frames (module docstring); never for windows of at most `exempt_frames` frames
    (`PeakSettings.broad_top_exempt_frames`)."""
    if n_frames <= exempt_frames or width_var_um2 <= 0.0:
        return False
    return float(np.sqrt(width_var_um2)) > BROAD_TOP_SHARE * span_um


def uniform_sigma_um(span_um: float) -> float:
    """The std (um) of a focus equally likely anywhere in a window `span_um` wide."""
    return span_um / float(np.sqrt(12.0))
