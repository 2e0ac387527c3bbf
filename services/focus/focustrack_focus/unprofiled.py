"""How a curve is read where the service has no entry for its metric.

A metric's constants on a microscope (its noise, its own offset from the plane a person
picks, its usual peak width) come from a microscope profile (`profile`, `focustrack focus
calibrate`). Without an entry, the service's own metrics (`metrics.METRICS`) are read with
the constants fitted on the instrument simulator (`peak.PeakSettings`' defaults: no offset
of their own, their short stacks exempt from the rule on a top broader than its window),
which their z-scores there bear out (docs/focus.md). A curve labelled with any other metric
(scores made by another program, on a microscope the service has never seen) has no such
record, and its reading assumes nothing that its curve cannot show:

- its offset from focus: a systematic sigma of a quarter of the optics' depth of field
  (`UNPROFILED_SYSTEMATIC_SHARE` of `PeakSettings.min_peak_sigma_um`, itself half the depth
  of field: the floor the optics put under an oversampled curve's sigma,
  `curve_checks.oversampled_floor_um`). A metric that weighs other spatial frequencies than
  the eye peaks a fraction of the depth of field from the plane a person picks, either way,
  by an amount no single curve shows: the optics bound it, the metric's name does not.
- whether a short window sees a top of its own: the rule on a top broader than its window
  (`curve_checks.broader_than_window`) applies to windows of every length.
- its noise: none on record, so a window's own estimate, from a few third differences, is
  all there is, and it may fall far short of the noise (a faint bump then reads as a clean
  top). Sigma and the top's chances take its upper bound at `UNPROFILED_NOISE_CONFIDENCE`
  (`noise_bound`; the confidence of a normal 2-sigma interval, which sigma stands for); the
  flat test and the candidates keep the estimate.
"""

from __future__ import annotations

from dataclasses import replace

from focustrack_focus.curve_checks import OVERSAMPLED_FLOOR_SHARE
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings

#: The systematic sigma of a metric the service has no entry for, as a share of
#: `PeakSettings.min_peak_sigma_um` (half the depth of field): a quarter of the depth of field.
UNPROFILED_SYSTEMATIC_SHARE = OVERSAMPLED_FLOOR_SHARE
#: The confidence of the upper bound on a curve's own noise estimate that sigma and the top's
#: chances take for such a metric (`PeakSettings.own_noise_confidence`).
UNPROFILED_NOISE_CONFIDENCE = 0.95


def unprofiled(peak: PeakSettings) -> PeakSettings:
    """`peak` for a metric the service has no entry for (module docstring): its systematic
    sigma at least UNPROFILED_SYSTEMATIC_SHARE of `min_peak_sigma_um`, no window exempt
    from the broad-top rule, and its own noise estimate bounded at (at least)
    UNPROFILED_NOISE_CONFIDENCE."""
    floor_um = UNPROFILED_SYSTEMATIC_SHARE * peak.min_peak_sigma_um
    return replace(
        peak,
        systematic_sigma_um=max(peak.systematic_sigma_um, floor_um),
        broad_top_exempt_frames=0,
        own_noise_confidence=max(peak.own_noise_confidence, UNPROFILED_NOISE_CONFIDENCE),
    )


def settings_without_entry(metric: str, base: FocusSettings) -> FocusSettings:
    """How a curve labelled `metric` is read where no profile has an entry for it: with
    `base` for one of the service's own metrics, else with `unprofiled(base.peak)`."""
    if metric in METRICS:
        return base
    return replace(base, peak=unprofiled(base.peak))
