"""Checks of a focus curve's shape that `peak.find_peak` applies besides its fit.

- A phase-like valley (`phase_valley`): an unstained specimen in brightfield loses its
  contrast in focus and reverses it across focus, so its curve falls to a sharp minimum
  at focus between two maxima, below the contrast of the far-out frames. A maximum-
  contrast reading of it lands one or two depths of field away; the curve is flagged
  `valley` (with `ambiguous`), and the minimum's z is given as the runner-up.
- An oversampled curve's sigma floor (`oversampled_floor_um`): where frames are far
  closer than the optics' depth of field, the fit's sub-step precision (a fraction of a
  tiny step) says nothing of how far the metric's own peak lies from the true focus,
  which is a matter of the optics, not of the step: sigma is kept above a share of the
  depth of field (`PeakSettings.min_peak_sigma_um` is half of it).
- A contrast too low to call, measured against the curve's own noise (`low_contrast_flat`):
  a share of the maximum is a stand-in for the noise where the curve is too short to
  measure it; a long clean curve whose peak stands many of its own noise spreads above
  its floor is no flat curve, however small its contrast (a 5x objective on pale tissue).
"""

from __future__ import annotations

import numpy as np

#: A valley: both maxima rise at least this share of the range above the minimum, and
#: both end frames at least `VALLEY_BELOW_ENDS` of it (the far-out frames keep contrast).
VALLEY_RISE_SHARE = 0.5
VALLEY_BELOW_ENDS = 0.25
#: ... and it is narrow: its width at half depth is at most this share of the distance
#: between the two maxima (two peaks on a background leave a broad trough between them).
VALLEY_WIDTH_SHARE = 0.5
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


def oversampled_floor_um(step_um: float, min_peak_sigma_um: float) -> float:
    """The sigma floor (um) of a peak read from frames `step_um` apart by optics whose
    narrowest peak has std `min_peak_sigma_um`: OVERSAMPLED_FLOOR_SHARE of it where the
    step is below OVERSAMPLED_STEP_SHARE of it, else 0 (module docstring)."""
    if step_um >= OVERSAMPLED_STEP_SHARE * min_peak_sigma_um:
        return 0.0
    return OVERSAMPLED_FLOOR_SHARE * min_peak_sigma_um


def low_contrast_flat(
    span: float, top: float, noise: float, clean: bool, min_contrast: float, min_snr: float
) -> bool:
    """Whether a curve of range `span` and maximum `top` is too low in contrast to hold a
    peak: below `min_contrast` of its maximum, unless its own noise estimate is clean and
    the range stands `min_snr` of those noise spreads above it (module docstring)."""
    if span > min_contrast * top:
        return False
    return not (clean and span > min_snr * noise)
