"""The upper confidence bound on a curve's own noise estimate (`noise_bound`), and a metric
the service has no entry for read with it (`unprofiled`): a faint bump on a window whose few
third differences say the noise is small is no confident reading."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from focustrack_focus.noise_bound import bound_factor, score_noise, used_differences
from focustrack_focus.pipeline import FocusSettings, focus_from_curve
from focustrack_focus.unprofiled import UNPROFILED_NOISE_CONFIDENCE, settings_without_entry


def test_the_bound_is_the_estimate_itself_at_confidence_zero_and_shrinks_with_more_frames() -> None:
    assert bound_factor(11, 5, 0.0) == 1.0
    assert bound_factor(3, 1, 0.95) == 1.0  # no estimate to bound
    with pytest.raises(ValueError, match="confidence"):
        bound_factor(11, 5, 1.0)
    window, full = bound_factor(11, 5, 0.95), bound_factor(100, 50, 0.95)
    assert window > 2.5 and 1.0 < full < 1.5  # 2 differences against 92
    assert bound_factor(11, 5, 0.975) > window  # a higher confidence, a wider bound
    # the runs score_noise takes: both sides of the top, or all where fewer than 2 are clear
    assert used_differences(11, 5) == (1, 1)
    assert used_differences(11, 0) == (6,)
    assert used_differences(5, 2) == (2,)


def test_the_bound_covers_the_noise_of_a_window_as_often_as_its_confidence_says() -> None:
    """11-frame windows on a steep quadratic top (third differences: zero) with white noise
    of std 1: the estimate alone falls short of the noise about half the time, its 95 %
    bound in about 5 % of windows."""
    rng = np.random.default_rng(7)
    frames = np.arange(11.0)
    top = -10.0 * (frames - 5.0) ** 2
    covered, raw_covered = [], []
    for _ in range(2000):
        s = top + rng.standard_normal(frames.size)
        estimate, clean = score_noise(s)
        assert clean and int(np.argmax(s)) == 5
        raw_covered.append(estimate >= 1.0)
        covered.append(estimate * bound_factor(s.size, 5, 0.95) >= 1.0)
    assert 0.93 <= np.mean(covered) <= 0.97
    assert np.mean(raw_covered) < 0.7


#: A window of 11 frames 2 steps (1 um) apart of WSI field 14's VOLLATH_F4 (scores / 1e9):
#: its faint bump tops 5 steps below the label (15 um); the 3 third differences clear of the
#: top say the noise is a tenth of the window's range, the full curve a third.
FAINT_Z_UM = np.arange(11.0, 22.0)
FAINT_SCORES = np.array(
    [
        194.935,
        200.406,
        199.556,
        196.716,
        196.713,
        196.987,
        195.941,
        195.7,
        196.337,
        196.698,
        193.435,
    ]
)
FAINT_FOCUS_UM = 15.0


def test_a_faint_bump_of_a_metric_without_an_entry_is_no_confident_miss() -> None:
    settings = settings_without_entry("VOLLATH_F4", FocusSettings())
    assert settings.peak.own_noise_confidence == UNPROFILED_NOISE_CONFIDENCE
    assert settings_without_entry("brenner", FocusSettings()).peak.own_noise_confidence == 0.0

    def covered(reading_settings: FocusSettings) -> bool:
        result = focus_from_curve(FAINT_Z_UM, FAINT_SCORES, reading_settings)
        assert result.best_z_um is not None and result.sigma_um is not None
        error_um = abs(result.best_z_um - FAINT_FOCUS_UM)
        assert error_um > 2.5  # the bump itself lies 5 steps (2.6 um) from the label
        return error_um <= 2.0 * result.sigma_um + 0.25  # 2 sigma and half a step

    # with the estimate itself, a confident reading 5 steps off (no warning flag either)
    without_bound = replace(settings, peak=replace(settings.peak, own_noise_confidence=0.0))
    assert not covered(without_bound)
    assert not focus_from_curve(FAINT_Z_UM, FAINT_SCORES, without_bound).flags
    assert covered(settings)
