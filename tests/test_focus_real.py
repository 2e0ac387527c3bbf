"""Real microscope stacks (../shared/data/real): the smear's focus lands on its labelled plane."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import focus_real
from focustrack.bench.focus import load_smear, load_yeast
from focustrack_core.domain import FocusFlag
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusSettings, focus_from_curve, focus_stack
from focustrack_focus.preprocess import Preprocess

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
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
    label_um = 17 * 0.3  # the source project's focus plane
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
    readings = focus_real.real_curves(WSI, ["BRENNER"], numbers=focus_real.REPORT_FIELDS)
    figures = focus_real.report(readings, focus_real.REPORT_FIELDS)["BRENNER"]
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
    field = focus_real.load_wsi_fields(WSI)[1]
    scores = field.scores["BRENNER"]
    below = np.arange(field.label_index - 5, field.label_index)  # ends one step below focus
    result = focus_from_curve(focus_real.WSI_STEP_UM * below, scores[below], FocusSettings())
    assert FocusFlag.EDGE_HIGH in result.flags and result.sigma_um is None
