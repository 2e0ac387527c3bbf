"""Learning a metric's constants on a microscope from labelled curves, and the figures that
judge them, on hand-made readings (errors and sigma in steps); test_focus_real.py learns
them on the real WSI curves."""

from __future__ import annotations

import numpy as np

from focustrack_core.domain import FocusFlag
from focustrack_focus.calibration import (
    CALIBRATION_COVERAGE,
    Calibration,
    Reading,
    coverage_with,
    cross_validate,
    field_offsets_covered,
    learn_relative_noise,
    learn_systematic_sigma,
    scored_fields,
    summarise,
    usability,
    windows,
)
from focustrack_focus.labelled_curves import LabelledCurve
from focustrack_focus.pipeline import focus_from_curve
from focustrack_focus.profile import UNUSABLE_RELATIVE_NOISE


def test_real_summary_counts_edges_coverage_and_silent_misses() -> None:
    """The figures of real curves read, on hand-made readings (errors and sigma in steps)."""
    high, low = frozenset({FocusFlag.EDGE_HIGH}), frozenset({FocusFlag.EDGE_LOW})
    rows = [
        Reading(2, "5x1", 0.4, 0.1, frozenset(), 0),  # within 1, covered (0.4 <= 0.2 + 0.5)
        Reading(2, "5x1", 1.5, 0.2, frozenset(), 0),  # within 2, not covered
        Reading(2, "5x1", 5.0, 0.5, frozenset(), 0),  # silent: far, no flag, outside 2 sigma
        Reading(2, "5x1", 5.0, None, high, 1),  # label above, edge_high: right
        Reading(2, "5x1", -5.0, None, high, -1),  # label below, edge_high: wrong
        Reading(2, "5x1", -5.0, 0.3, frozenset({FocusFlag.MULTI_PEAK}), -1),  # warned
        Reading(2, "5x1", None, None, low, -1),  # right
    ]
    figures = summarise(rows)
    assert figures["within_1_step"] == 1 / 3 and figures["within_2_steps"] == 2 / 3
    assert figures["coverage_2sigma"] == 1 / 3
    assert figures["edge_right"] == 2 / 4 and figures["edge_wrong"] == 1 / 4
    assert figures["silent_miss"] == 1 / 7
    shapes = {w.kind for w in windows(100, 50)}
    assert "full" in shapes and {"5x1", "11x3"} <= shapes


def reading(error_steps: float, sigma_steps: float, kind: str = "full") -> Reading:
    return Reading(1, kind, error_steps, sigma_steps, frozenset(), 0)


def test_the_systematic_sigma_is_the_least_that_covers_the_fit_readings() -> None:
    covered = [reading(0.4, 0.1), reading(0.3, 0.1, "5x1")]
    assert learn_systematic_sigma(covered) == 0.0  # a clear pick keeps its sigma
    # one step off with sigma 0.1: |e| <= 2 hypot(0.1, s) + 0.5 from s = 0.24, on the grid 0.25
    biased = covered + [reading(1.0, 0.1, "5x1")] * 19 + [reading(0.0, 0.1)] * 19
    assert learn_systematic_sigma(biased) == 0.25
    assert coverage_with(biased, 0.2) < CALIBRATION_COVERAGE


def test_the_systematic_sigma_stops_at_the_median_sigma_target() -> None:
    """A measure whose picks stray three steps needs more systematic sigma than the median
    sigma target allows: none is learnt (None), and an all-flat part asks for nothing."""
    covered = [reading(0.0, 0.1)] * 20
    straying = covered + [reading(3.0, 0.1, "5x1")] * 20
    assert learn_systematic_sigma(straying) is None
    assert learn_systematic_sigma(straying, cap_steps=2.0) == 1.25
    flat = Reading(1, "5x1", None, None, frozenset({FocusFlag.FLAT}), 0)
    assert learn_systematic_sigma(covered + [flat] * 5) == 0.0


def test_a_measure_is_unusable_when_most_windows_are_flat_or_no_sigma_covers() -> None:
    flat = Reading(1, "5x1", None, None, frozenset({FocusFlag.FLAT}), 0)
    measured = reading(0.0, 0.1, "5x1")
    full_flat = Reading(1, "full", None, None, frozenset({FocusFlag.FLAT}), 0)
    # full curves do not count towards the flat share: half the windows flat is usable
    assert usability([full_flat] * 9 + [flat, measured], 0.0) == ""
    assert "flat" in usability([flat, flat, measured], 0.0)
    assert "no systematic sigma" in usability([measured], None)
    # an unusable measure's settings read every curve flat, even a clear peak
    unusable = Calibration(0.003, None, "most windows flat")
    z_um = np.arange(11.0)
    peak = 100.0 + 50.0 * np.exp(-0.5 * (z_um - 5.0) ** 2)
    assert focus_from_curve(z_um, peak, unusable.settings()).flags == {FocusFlag.FLAT}
    assert focus_from_curve(z_um, peak, Calibration(0.003).settings()).flags == set()


def test_the_systematic_sigma_alone_covers_each_fields_offset() -> None:
    """A field whose full curve peaks 0.85 steps from the label, well inside its own sigma:
    its windows carry the same offset with far less sigma, so the systematic sigma alone
    must cover it (2 s + 0.5 >= 0.85: s = 0.2 on the grid), whatever the windows say."""
    fields = [Reading(n, "full", 0.1, 0.3, frozenset(), 0) for n in range(1, 10)]
    offset = Reading(10, "full", -0.85, 0.3, frozenset(), 0)
    windows_near = [reading(0.1, 0.1, "11x3")] * 50
    assert learn_systematic_sigma(fields + windows_near) == 0.0
    assert field_offsets_covered([*fields, offset], 0.15) == 0.9
    assert learn_systematic_sigma([*fields, offset, *windows_near]) == 0.2


def labelled(number: int, scores: np.ndarray) -> LabelledCurve:
    """A field of 0.5 um steps labelled at 10 um."""
    return LabelledCurve(number, 0.5 * np.arange(scores.size), {"M": scores}, 10.0)


def test_a_field_whose_scores_are_all_zero_is_left_out_of_its_metric() -> None:
    """Its noise is no share of a maximum (0 / 0): it made the profile entry refuse NaN."""
    z_um = 0.5 * np.arange(40)
    peak = 50.0 + 1000.0 * np.exp(-0.5 * ((z_um - 10.0) / 1.8) ** 2)
    fields = [labelled(n, peak) for n in (1, 2, 3)] + [labelled(4, np.zeros(40))]
    kept, blank = scored_fields(fields, "M")
    assert [f.number for f in kept] == [1, 2, 3] and blank == [4]
    constants, folds = cross_validate(kept, "M", 3)
    assert constants.usable and len(folds) == 3
    assert constants.entry().relative_noise == constants.relative_noise  # a profile takes it


def test_noise_above_a_curves_maximum_is_the_unusable_floor_not_above_it() -> None:
    """Scores below 0 but a hair: the noise is hundreds of times their maximum, a share the
    profile refused (relative_noise above 1); it reads as the floor that turns it off."""
    noise = np.random.default_rng(4).normal(0.0, 1.0, 40)
    fields = [labelled(n, noise - noise.max() + 0.01) for n in (1, 2)]
    assert learn_relative_noise(fields, "M") == UNUSABLE_RELATIVE_NOISE
    constants, _ = cross_validate(fields, "M", 2)
    assert not constants.usable and constants.entry().relative_noise == UNUSABLE_RELATIVE_NOISE
