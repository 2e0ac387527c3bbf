"""Real microscope stacks (../shared/data/real): the smear's focus lands on its labelled plane."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_core.fusion import fuse_planes
from focustrack_focus import calibration
from focustrack_focus.labelled_curves import wsi_curves
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusSettings, focus_from_curve, focus_stack
from focustrack_focus.preprocess import Preprocess
from focustrack_focus.real_data import (
    WSI_STEP_UM,
    YEAST_FOCUS_PLANE,
    load_smear,
    load_wsi_fields,
    load_yeast,
)

#: ../shared/data/real beside the checkout (services/focus/tests/ is three folders down).
REAL = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real"
SMEAR, YEAST = REAL / "lip_smear_zstack", REAL / "yeast_brightfield_zstack"
WSI = REAL / "wsi_focus_curves"
pytestmark = pytest.mark.skipif(
    not REAL.is_dir(), reason=f"real data folder {REAL} is missing (see its README)"
)
#: These small frames are not oversampled like a slide scanner's: a 1 px low-pass.
PREPROCESS = Preprocess(lowpass_sigma_px=1.0)


@pytest.mark.parametrize("metric", list(METRICS))
def test_smear_focus_lands_on_plane_zero(metric: str) -> None:
    frames, plane = load_smear(SMEAR)
    assert frames.shape[0] == 19
    result = focus_stack(frames, plane, FocusSettings(PREPROCESS, metric))
    assert result.flags == frozenset()
    assert round(result.best_z_um) == 0, result.best_z_um


def test_unstained_yeast_focus_is_the_contrast_minimum() -> None:
    frames, z_um = load_yeast(YEAST)
    label_um = YEAST_FOCUS_PLANE * 0.3  # the source project's focus plane
    valley = FocusSettings(PREPROCESS, peak=PeakSettings(mode=PeakMode.VALLEY))
    at_valley = focus_stack(frames, z_um, valley)
    assert at_valley.best_z_um == pytest.approx(label_um, abs=0.45)  # 1.5 planes
    # the usual maximum-contrast reading lands far from focus on this specimen
    at_max = focus_stack(frames, z_um, FocusSettings(PREPROCESS))
    assert abs(at_max.best_z_um - label_um) > 1.5
    assert np.argmin(at_max.scores) in range(15, 19)


@pytest.mark.slow  # about 25 s: 5 000 windows
def test_wsi_curves_gradient_metric_meets_the_targets_on_held_out_fields() -> None:
    """Brenner on the even fields (the constants were chosen on the odd ones): full curves
    and scanner windows land within a step, inside 2 sigma, with edge flags toward focus."""
    readings = calibration.real_curves(WSI, ["BRENNER"], numbers=calibration.REPORT_FIELDS)
    figures = calibration.report(readings, calibration.REPORT_FIELDS)["BRENNER"]
    for part in ("full", "windows"):
        assert figures[part]["within_1_step"] >= 0.97, part
        assert figures[part]["coverage_2sigma"] >= 0.92, part
        assert figures[part]["silent_miss"] <= 0.001, part
    assert figures["windows_11x3"]["median_sigma_steps"] <= 0.75
    assert figures["windows"]["edge_right"] >= 0.98
    assert figures["windows"]["edge_wrong"] <= 0.005


def test_wsi_window_ending_below_focus_points_up() -> None:
    """A 5-frame window just below focus: the curve rises to its last frame, so edge_high
    (toward focus), never a shoulder read as a peak."""
    field = load_wsi_fields(WSI)[1]
    scores = field.scores["BRENNER"]
    below = np.arange(field.label_index - 5, field.label_index)  # ends one step below focus
    result = focus_from_curve(WSI_STEP_UM * below, scores[below], FocusSettings())
    assert FocusFlag.EDGE_HIGH in result.flags and result.sigma_um is None


@pytest.mark.slow  # about 20 s
def test_wsi_vollath_is_unusable_on_this_microscope_and_reads_flat() -> None:
    """VOLLATH_F4 is all but blind on this microscope: the fit fields alone declare it
    unusable, and then every full curve and window of every field is flat (no silent miss)
    while the gradient measure next to it stays usable."""
    constants = calibration.calibrate(WSI, ["VOLLATH_F4", "BRENNER"])
    assert constants["BRENNER"].usable
    vollath = constants["VOLLATH_F4"]
    assert vollath.relative_noise > 0.002  # ten times the gradient metrics' noise
    assert not vollath.usable and "flat" in vollath.unusable_because
    settings = vollath.settings()
    for field in wsi_curves(load_wsi_fields(WSI)):
        readings = calibration.read_field(field, "VOLLATH_F4", settings)
        assert all(r.flags == {FocusFlag.FLAT} for r in readings), field.number


@pytest.mark.slow  # about 15 s
def test_wsi_jpeg_systematic_sigma_learnt_on_fit_fields_covers_held_out_fields() -> None:
    """JPEG size peaks up to a step from the plane a person picks, either way: the
    systematic sigma learnt on the odd fields covers the even ones, and stays small."""
    constants = calibration.calibrate(WSI, ["JPEG"])
    assert 0.1 <= constants["JPEG"].systematic_sigma_steps <= 0.5
    readings = calibration.real_curves(WSI, ["JPEG"], calibration.REPORT_FIELDS, constants)
    figures = calibration.report(readings, calibration.REPORT_FIELDS)["JPEG"]
    for part in ("full", "windows"):
        assert figures[part]["coverage_2sigma"] >= 0.92, part
        assert figures[part]["silent_miss"] <= 0.001, part
    assert figures["windows_11x3"]["median_sigma_steps"] <= 0.75


def test_fusing_a_real_smears_planes_takes_each_region_from_the_plane_in_focus() -> None:
    """A tile's kept frames fused (`focustrack_core.fusion`) on real texture: halves of
    the labelled focus plane and of a plane 3 steps off, swapped between two frames,
    come back from the focused plane; the real planes -2, 0, 2 fuse as sharp as plane 0."""
    frames, plane = load_smear(SMEAR)
    focused, off = frames[plane == 0][0], frames[plane == -3][0]
    half = focused.shape[1] // 2
    left_sharp, right_sharp = focused.copy(), off.copy()
    left_sharp[:, half:], right_sharp[:, half:] = off[:, half:], focused[:, half:]
    fused = fuse_planes(np.stack([left_sharp, right_sharp]))
    from_focus = np.all(fused == focused, axis=2)
    seam = 8  # the sharpness window straddles the seam there
    assert from_focus[:, : half - seam].mean() > 0.95
    assert from_focus[:, half + seam :].mean() > 0.95

    def brenner(image: np.ndarray) -> float:
        grey = image.astype(np.float64).mean(axis=2)
        return float(((grey[:, 2:] - grey[:, :-2]) ** 2).mean())

    three = np.stack([frames[plane == z][0] for z in (-2, 0, 2)])
    assert (
        brenner(fuse_planes(three)) >= brenner(focused) > max(brenner(three[0]), brenner(three[2]))
    )
