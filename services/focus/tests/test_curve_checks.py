"""The curve's shape checks (`curve_checks`): a phase-like valley is flagged, an oversampled
curve keeps a sigma tied to the optics, and a low contrast is judged against the curve's
own noise; on real curves (../shared/data/real) where they exist."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.curve_checks import (
    OVERSAMPLED_FLOOR_SHARE,
    SPIKE_SHARE,
    between_maxima,
    broader_than_window,
    low_contrast_flat,
    narrowest_peak_sigma_um,
    oversampled_floor_um,
    phase_valley,
    tied_with_end,
    twin_maxima,
    uniform_sigma_um,
)
from focustrack_focus.despike import despike
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakMode, PeakSettings, find_peak
from focustrack_focus.pipeline import FocusSettings, focus_stack
from focustrack_focus.real_data import YEAST_FOCUS_PLANE, load_wsi_fields, load_yeast

REAL = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is missing (its README)")


def gaussian(z: np.ndarray, centre: float, width: float) -> np.ndarray:
    return np.exp(-0.5 * ((z - centre) / width) ** 2)


def test_a_sharp_minimum_between_two_maxima_is_a_valley_two_peaks_on_a_floor_are_not() -> None:
    z = np.arange(0.0, 10.01, 0.3)
    # contrast reversing across focus at 5 um: high far out, zero in focus
    phase = 1.0 - gaussian(z, 5.0, 0.6) + 0.2 * gaussian(z, 3.5, 1.0) + 0.2 * gaussian(z, 6.5, 1)
    assert phase_valley(z, phase) == pytest.approx(5.0, abs=0.3)
    two_peaks = 0.05 + gaussian(z, 2.5, 0.8) + 0.8 * gaussian(z, 7.5, 0.8)  # a broad trough
    assert phase_valley(z, two_peaks) is None
    single = 0.05 + gaussian(z, 5.0, 1.0)
    assert phase_valley(z, single) is None
    fit = find_peak(z, 100.0 * phase)
    assert {FocusFlag.VALLEY, FocusFlag.AMBIGUOUS} <= fit.flags
    assert fit.runner_up_z_um == pytest.approx(5.0, abs=0.3)
    assert fit.chosen_probability is not None and fit.chosen_probability <= 0.5
    # read as a valley (the mode for unstained specimens), it is the focus, not a warning
    valley = find_peak(z, 100.0 * phase, PeakSettings(mode=PeakMode.VALLEY))
    assert FocusFlag.VALLEY not in valley.flags and abs(valley.z_um - 5.0) < 0.15


@needs_real
@pytest.mark.parametrize("metric", ["tenengrad", "brenner", "vollath_f4"])
def test_the_real_unstained_yeast_is_recognised_as_a_valley(metric: str) -> None:
    frames, z_um = load_yeast(REAL / "yeast_brightfield_zstack")
    result = focus_stack(frames, z_um, FocusSettings(metric=metric))
    assert {FocusFlag.VALLEY, FocusFlag.AMBIGUOUS} <= result.flags
    assert result.runner_up_z_um is not None
    assert abs(result.runner_up_z_um / 0.3 - YEAST_FOCUS_PLANE) <= 1.0  # within a frame


#: Two scans' first stacks on the simulator's unstained red cells (4 um steps from -24 to
#: 24 um, Tenengrad; focus at -0.08 um on both tiles): far out of focus the defocus contrast
#: fades again, so each end frame is low (seed 2's ends lower than the far side of the
#: valley's own maxima by little; seed 0's far end the curve's lowest frame).
COARSE_Z_UM = np.arange(-24.0, 24.1, 4.0)
COARSE_UNSTAINED = {
    0: [0.014, 0.0171, 0.017, 0.028, 0.0527, 0.046, 0.01256, 0.0517, 0.032, 0.0206, 0.0158,
        0.0105, 0.00703],
    2: [0.0117, 0.0144, 0.0135, 0.0216, 0.0436, 0.043, 0.0004, 0.0431, 0.0315, 0.0187, 0.0164,
        0.0116, 0.0077],
}  # fmt: skip


@pytest.mark.parametrize("seed", sorted(COARSE_UNSTAINED))
def test_a_coarse_stack_read_as_a_valley_finds_the_minimum_between_its_maxima(seed: int) -> None:
    scores = np.array(COARSE_UNSTAINED[seed])
    assert twin_maxima(scores) == (4, 7)  # -8 and 4 um, the valley at 0 between them
    fit = find_peak(COARSE_Z_UM, scores, PeakSettings(mode=PeakMode.VALLEY))
    # read whole, turned upside down, its fading ends rose like a peak beyond the window
    # (seed 2: 24 um, edge_high) or its noise looked too large for any peak (seed 0: flat)
    assert fit.z_um is not None and abs(fit.z_um + 0.08) < 0.5, fit
    assert fit.sigma_um is not None and fit.sigma_um > abs(fit.z_um + 0.08)
    assert not fit.flags


#: Two more scans' first stacks (4 um steps from -28 to 28 um, Tenengrad, the focus service
#: in valley mode, seed 1's surface: focus at -1.98 um), on 10 x 10 slides. Red cells: a
#: valley between -8 and 4 um that sinks 25 % of the range (the rest is the contrast fading
#: far out). Thick cells in culture: no rise again after the dip at 0 um, the contrast
#: fading fast above focus. Read whole, turned upside down, both were their faded ends
#: (+28 um, `edge_high`), and the scans lost the surface (36 of 100 tiles in focus).
COARSE_28_Z_UM = np.arange(-28.0, 28.1, 4.0)
COARSE_28 = {
    "phase-blood": [0.01123, 0.01405, 0.01521, 0.01862, 0.03319, 0.04632, 0.02857, 0.02876,
                    0.03868, 0.0194, 0.01469, 0.01118, 0.00702, 0.00631, 0.00601],
    "phase-cells": [0.00329, 0.00341, 0.00352, 0.00361, 0.00397, 0.0046, 0.00461, 0.00384,
                    0.00392, 0.00307, 0.00268, 0.00231, 0.00192, 0.0016, 0.00156],
}  # fmt: skip


def test_a_coarse_valley_deep_against_its_noise_or_near_the_top_is_read_not_the_faded_end() -> None:
    blood, cells = (np.array(COARSE_28[name]) for name in ("phase-blood", "phase-cells"))
    assert twin_maxima(blood) == (5, 8)  # 5 of its noise sigmas deep, not half the range
    valley = PeakSettings(mode=PeakMode.VALLEY)
    fit = find_peak(COARSE_28_Z_UM, blood, valley)
    assert fit.z_um == pytest.approx(-1.98, abs=0.5) and not fit.flags
    # no two maxima: read within VALLEY_REACH_UM of the strongest contrast (-4 um)
    assert twin_maxima(cells) is None
    near_z, _ = between_maxima(COARSE_28_Z_UM, cells)
    assert near_z.tolist() == [-12.0, -8.0, -4.0, 0.0, 4.0]
    fit = find_peak(COARSE_28_Z_UM, cells, valley)
    assert fit.z_um is not None and abs(fit.z_um + 1.98) < 4.0, fit
    assert not fit.flags & {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH}


#: A scan's first stack on a tile of sparse cells in culture (seed 4, 4 um steps, valley
#: mode; focus at +1.60 um, a valley 1.3 um wide that no frame of it falls in): far-out
#: contrast wandering by noise, with maxima at -24 and -4 um. Cropped to the frames between
#: them and judged against no noise, it read as a valley at -9.98 +- 0.96 um, and the scan
#: followed it 40 um off the cells (11 of 54 tiles in focus).
COARSE_SPARSE_CELLS = [0.0024508, 0.0023764, 0.0022115, 0.0020014, 0.0019979, 0.002422,
                       0.0021935, 0.0022949, 0.0019979, 0.0016029, 0.0016106, 0.0018253,
                       0.0019671]  # fmt: skip


def test_a_valley_no_deeper_than_the_whole_stack_s_noise_is_flat() -> None:
    scores = np.array(COARSE_SPARSE_CELLS)
    fit = find_peak(COARSE_Z_UM, scores, PeakSettings(mode=PeakMode.VALLEY))
    assert fit.z_um is None and FocusFlag.FLAT in fit.flags
    # the same stack read as a peak is flat too: a valley must stand as much noise as a peak
    assert FocusFlag.FLAT in find_peak(COARSE_Z_UM, scores, PeakSettings()).flags
    # (the red cells' first stacks above, whose valleys stand far deeper, are still read)


def test_only_a_dip_of_half_the_range_between_two_maxima_is_a_valley_to_crop_to() -> None:
    z = np.arange(-3.0, 3.01, 0.5)
    v_alone = np.abs(z) + 0.1  # a short stack about the focus: the V, its ends its maxima
    assert twin_maxima(v_alone) == (0, z.size - 1)  # read whole
    assert twin_maxima(z + 5.0) is None  # one side of it
    assert twin_maxima(0.05 + gaussian(z, 0.0, 1.0)) is None  # a stained specimen's peak
    shallow = 1.0 - 0.15 * gaussian(z, 0.0, 0.5) - 0.5 * gaussian(np.abs(z), 3.0, 0.5)
    assert twin_maxima(shallow) is None  # a dip of under half the range (the ends lower)
    fading = np.abs(z) * np.exp(-np.abs(z) / 1.5)  # maxima at +-1.5 um, fading beyond
    assert twin_maxima(fading) == (3, 9)
    valley = find_peak(z, fading, PeakSettings(mode=PeakMode.VALLEY))
    assert valley.z_um == pytest.approx(0.0, abs=0.05) and not valley.flags


@needs_real
@pytest.mark.parametrize("metric", ["tenengrad", "brenner", "vollath_f4"])
def test_the_real_unstained_yeast_read_as_a_valley_is_in_focus(metric: str) -> None:
    frames, z_um = load_yeast(REAL / "yeast_brightfield_zstack")
    valley = PeakSettings(mode=PeakMode.VALLEY)
    result = focus_stack(frames, z_um, FocusSettings(metric=metric, peak=valley))
    assert not result.flags  # the faded far-out frames are no second peak
    assert result.best_z_um is not None and result.sigma_um is not None
    assert abs(result.best_z_um / 0.3 - YEAST_FOCUS_PLANE) <= 1.0  # within a frame
    assert abs(result.best_z_um - 0.3 * YEAST_FOCUS_PLANE) < 2.0 * result.sigma_um


@needs_real
def test_no_real_wsi_curve_reads_as_a_valley() -> None:
    """The stained whole-slide fields (two peaks on many: debris) never look phase-like."""
    for field in load_wsi_fields(REAL / "wsi_focus_curves"):
        z_um = 0.5 * np.arange(field.n_positions)
        for metric in ("BRENNER", "_3_3_SOBEL", "SQUARED_GRADIENT", "NORMALIZED_VARIANCE"):
            assert FocusFlag.VALLEY not in find_peak(z_um, field.scores[metric]).flags


def test_the_oversampled_floor_is_a_share_of_the_depth_of_field_only_below_its_eighth() -> None:
    assert oversampled_floor_um(0.25, 0.25) == 0.0  # a 100x objective's usual steps
    assert oversampled_floor_um(0.05, 0.25) == OVERSAMPLED_FLOOR_SHARE * 0.25


def test_fine_steps_cannot_make_a_one_frame_sigma_over_a_three_frame_miss() -> None:
    """0.05 um steps over a peak whose metric lies 0.14 um (2.8 frames) from the focus
    (a lopsided peak: the metric weighs other frequencies than the eye): without the floor
    the fit's sigma is about a frame, a confident miss; with it the miss is inside 2 sigma."""
    z = np.arange(-1.5, 1.501, 0.05)
    truth_um = 0.0
    scores = 1000.0 * (0.1 + gaussian(z, truth_um + 0.14, 0.35))
    scores += np.random.default_rng(3).normal(0.0, 0.5, z.size)
    fit = find_peak(z, scores)
    assert fit.sigma_um is not None and fit.z_um is not None
    assert fit.sigma_um >= OVERSAMPLED_FLOOR_SHARE * PeakSettings().min_peak_sigma_um
    assert abs(fit.z_um - truth_um) <= 2.0 * fit.sigma_um
    coarse = find_peak(z[::6], scores[::6])  # 0.3 um steps: the step-based sigma, no floor
    assert coarse.sigma_um is not None and coarse.sigma_um < 0.1


def test_a_low_contrast_peak_clear_of_its_own_noise_is_not_flat() -> None:
    """A pale specimen under a 5x objective: the curve changes by 0.5 % of its level, but
    smoothly, 50 of its own noise spreads; pure noise of the same level stays flat."""
    z = np.arange(-20.0, 20.01, 2.0)
    rng = np.random.default_rng(4)
    pale = 1000.0 * (1.0 + 0.005 * gaussian(z, 3.0, 6.0)) + rng.normal(0.0, 0.1, z.size)
    fit = find_peak(z, pale)
    assert FocusFlag.FLAT not in fit.flags
    assert fit.z_um is not None and abs(fit.z_um - 3.0) <= 2.0  # within a frame
    noise = 1000.0 + rng.normal(0.0, 0.5, z.size)
    assert FocusFlag.FLAT in find_peak(z, noise).flags
    # a short window: no clean noise of its own, so the contrast share still decides
    peaked = np.array([996.0, 998.0, 1000.0, 998.0, 996.0])
    assert low_contrast_flat(peaked, 1000.0, 0.01, False, 0.01, 10.0)
    assert not low_contrast_flat(peaked, 1000.0, 0.01, True, 0.01, 10.0)
    # a clean, pale wander that hardly rises above its ends (brightness alone changing
    # with z, Micro-Manager's demo camera): flat still
    wander = np.array([1000.0, 999.0, 1001.5, 998.0, 999.5, 1001.0])
    assert low_contrast_flat(wander, 1001.5, 0.1, True, 0.01, 10.0)
    contrasted = np.array([950.0, 1000.0, 950.0])
    assert not low_contrast_flat(contrasted, 1000.0, 100.0, False, 0.01, 10.0)


@pytest.mark.parametrize("metric", sorted(METRICS))
def test_a_low_contrast_5x_stack_is_not_flat(metric: str, render) -> None:
    """Simulated cells seen through a 5x objective (defocus blurs slowly: a deep depth of
    field, 2 um steps) at 3 % of their contrast, with a camera's noise: a person sees the
    focus at plane 10 of 19; no metric may call the stack flat."""
    z_um = np.arange(-18.0, 18.01, 2.0)
    sharp = render(96, z_um, 0.0, 11).astype(np.float64)
    level = float(np.median(sharp))
    rng = np.random.default_rng(5)
    pale = level + 0.03 * (sharp - level) + rng.normal(0.0, 2.0, sharp.shape)
    result = focus_stack(
        np.clip(pale, 0, 4095).astype(np.uint16), z_um, FocusSettings(metric=metric)
    )
    assert FocusFlag.FLAT not in result.flags, metric
    assert result.best_z_um is not None
    within_a_frame = abs(result.best_z_um) <= 2.0
    assert within_a_frame or result.flags & {FocusFlag.AMBIGUOUS, FocusFlag.MULTI_PEAK}


def test_a_top_hidden_under_a_far_peaks_foot_makes_the_edge_uncertain() -> None:
    """Focus at 20 um, and debris 12 um above it whose broad foot rises over the focus's top:
    an 11x3 window around the focus sees no top of its own, only a shoulder on the way to
    its high end. The edge flag toward the debris comes with the shoulder as the runner-up
    and no certainty; on the focus's own flank, with no debris, the edge stays certain."""
    z = np.arange(0.0, 50.0, 0.5)
    rng = np.random.default_rng(1)
    focus = 50.0 + 1000.0 * gaussian(z, 20.0, 1.5) + rng.normal(0.0, 1.0, z.size)
    debris = focus + 8000.0 * gaussian(z, 32.0, 4.0)
    window = 32 + 3 * np.arange(11)  # 16 .. 31 um
    fit = find_peak(z[window], debris[window])
    assert {FocusFlag.EDGE_HIGH, FocusFlag.MULTI_PEAK, FocusFlag.AMBIGUOUS} <= fit.flags
    assert fit.runner_up_z_um is not None and abs(fit.runner_up_z_um - 20.0) <= 1.0
    assert fit.chosen_probability is not None and fit.chosen_probability <= 0.5
    below = np.arange(20, 38, 2)  # 10 .. 18 um: the focus's rising flank alone
    flank = find_peak(z[below], focus[below])
    assert flank.flags == {FocusFlag.EDGE_HIGH} and flank.chosen_probability == 1.0


@needs_real
def test_a_top_resting_on_a_one_frame_dip_at_the_window_end_is_ambiguous() -> None:
    """WSI field 5 has a one-frame dip 4 steps above its focus: a window that starts on it
    sees a 'peak' on its second frame, narrower than any of this microscope's peaks. With the
    metric's usual width (a profile's) that top is ambiguous, the window's low end (toward
    the focus) the runner-up; without it, nothing tells it from a real top."""
    (field,) = [f for f in load_wsi_fields(REAL / "wsi_focus_curves") if f.number == 5]
    scores = field.scores["BRENNER"]
    window = np.arange(field.label_index + 4, field.label_index + 13)  # 9 x 1 from the dip
    z_um = 0.5 * window
    blind = find_peak(z_um, scores[window])
    assert blind.flags == frozenset() and blind.z_um is not None  # the false top, confident
    informed = find_peak(z_um, scores[window], PeakSettings(curve_fwhm_um=4.4))
    assert {FocusFlag.AMBIGUOUS, FocusFlag.MULTI_PEAK} <= informed.flags
    assert informed.runner_up_z_um == z_um[0] and informed.chosen_probability == 0.5


@needs_real
def test_a_top_tied_with_the_window_end_frame_is_ambiguous_without_a_profile() -> None:
    """WSI field 5's one-frame dip, as the first frame of a 5 x 2 window: the next frame
    stands 2 % of the window's range above it, a 'top' that one dipped end frame makes. With
    no profile the window says so (ambiguous, the end the runner-up); a top that stands
    clear of the end frame, and a three-frame stack, are not touched."""
    (field,) = [f for f in load_wsi_fields(REAL / "wsi_focus_curves") if f.number == 5]
    scores = field.scores["BRENNER"]
    window = field.label_index + 4 + 2 * np.arange(5)
    fit = find_peak(0.5 * window, scores[window])
    assert {FocusFlag.AMBIGUOUS, FocusFlag.MULTI_PEAK} <= fit.flags
    assert fit.runner_up_z_um == 0.5 * window[0] and fit.chosen_probability == 0.5
    assert fit.sigma_um is not None  # still the window's reading, with its own sigma
    z = np.arange(9.0)
    clear = find_peak(z, gaussian(z, 1.4, 1.5))
    assert clear.flags == frozenset() and clear.chosen_probability == 1.0
    assert tied_with_end(np.array([0.99, 1.0, 0.5, 0.2, 0.1]), 1, 0, 0.05)
    assert not tied_with_end(np.array([0.99, 1.0, 0.5]), 1, 0, 0.05)


@needs_real
def test_despike_replaces_the_dip_not_the_end_frame_its_dip_spoils() -> None:
    """WSI field 5's one-frame dip as the second frame of a 9 x 1 window on the falling
    flank: the end frame's extrapolation runs through the dip, so judged one at a time the
    end frame looks the worse outlier. The dip is the frame whose replacement explains
    the others; with the metric's usual peak width (4.3 um, a profile's) it is no peak."""
    (field,) = [f for f in load_wsi_fields(REAL / "wsi_focus_curves") if f.number == 5]
    window = field.label_index + 3 + np.arange(9)
    z, scores = 0.5 * window, field.scores["BRENNER"][window]
    out = despike(z, scores, 0.0, narrowest_peak_sigma_um(0.25, 4.3))
    assert out[0] == scores[0] and scores[2] < out[1] < scores[0]  # the dip, filled in
    assert np.array_equal(out[2:], scores[2:])
    # with the optics' narrowest peak alone (no profile), 0.5 um steps may hold a dip
    assert np.array_equal(despike(z, scores, 0.0, narrowest_peak_sigma_um(0.25, None)), scores)
    assert narrowest_peak_sigma_um(0.25, 4.3) == pytest.approx(SPIKE_SHARE * 4.3 / 2.3548, 1e-3)


@pytest.mark.parametrize(
    ("step_um", "scores", "best_z_um"),
    [
        (5.0, [1, 5, 1, 1, 1], 5.0),  # was the low end, edge_low: the end frame "an outlier"
        (1.0, [1, 5, 1, 1, 1], 1.0),  # was flat: the peak removed as a spike
        (2.0, [1, 1, 5, 1, 1, 1, 1], 4.0),  # was flat
        (1.0, [2, 5, 1, 2, 1], 1.0),  # was the low end, the peak not even the runner-up
    ],
)
def test_a_one_frame_peak_between_frames_four_sigmas_apart_is_read_there(
    step_um: float, scores: list[float], best_z_um: float
) -> None:
    """Where frames are 4 or more of the narrowest peak's sigmas apart (0.25 um), a peak
    on one frame is possible (docs/focus.md, "Outliers"): it is read, not removed; at
    0.5 um steps it is impossible, a spike, and the curve is flat."""
    z = step_um * np.arange(len(scores))
    fit = find_peak(z, np.array(scores, dtype=float))
    assert fit.z_um == pytest.approx(best_z_um, abs=0.15 * step_um), fit
    assert not fit.flags & {FocusFlag.FLAT, FocusFlag.EDGE_LOW}, fit
    spike = find_peak(0.5 * np.arange(5), np.array([1.0, 5.0, 1.0, 1.0, 1.0]))
    assert spike.flags == {FocusFlag.FLAT}


def test_a_top_broader_than_its_window_is_ambiguous_anywhere_in_it() -> None:
    """A window of 9 frames on a gentle bump whose Gaussian std is twice the window's span
    sees curvature and no top of its own: ambiguous, its sigma at least that of a focus
    equally likely anywhere in the window. A peak that fits in the window, and a 5-frame
    stack placed around a prediction (which sees only the top by design), are untouched."""
    z = np.arange(9.0)  # span 8 um
    broad = find_peak(z, 1.0 + gaussian(z, 3.0, 16.0))
    assert FocusFlag.AMBIGUOUS in broad.flags and broad.sigma_um is not None
    assert broad.sigma_um >= uniform_sigma_um(8.0) == pytest.approx(8.0 / np.sqrt(12.0))
    assert broad.chosen_probability is not None and broad.chosen_probability <= 0.5
    narrow = find_peak(z, gaussian(z, 3.7, 1.5))
    assert narrow.flags == frozenset() and narrow.sigma_um is not None
    assert narrow.sigma_um < 0.5
    short = find_peak(z[:5], 1.0 + gaussian(z[:5], 2.2, 16.0))
    assert FocusFlag.AMBIGUOUS not in short.flags
    assert broader_than_window(5.0**2, 4.0, 9) and not broader_than_window(3.0**2, 4.0, 9)
    assert not broader_than_window(5.0**2, 4.0, 5) and not broader_than_window(0.0, 4.0, 9)


@needs_real
def test_vollath_f4s_faint_real_bumps_are_not_read_as_located_tops() -> None:
    """Vollath F4 on the shared WSI curves is a faint bump under noise: without a profile,
    the 11 x 3 windows whose fitted top is broader than the window say so (ambiguous), and
    their 2-sigma coverage holds (it was 69-78 % before the rule)."""
    from focustrack_focus.calibration import parts, read_fields
    from focustrack_focus.labelled_curves import wsi_curves

    fields = wsi_curves(
        [f for f in load_wsi_fields(REAL / "wsi_focus_curves") if f.number % 2 == 1]
    )
    figures = parts(read_fields(fields, "VOLLATH_F4", FocusSettings()))["windows_11x3"]
    assert figures["coverage_2sigma"] >= 0.85
    assert figures["ambiguous"] > 0.1
