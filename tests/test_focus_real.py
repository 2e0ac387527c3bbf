"""Real microscope stacks (../shared/data/real): the smear's focus lands on its labelled plane."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from focustrack.bench.focus import load_smear, load_yeast
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusSettings, focus_stack
from focustrack_focus.preprocess import Preprocess

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"
SMEAR, YEAST = REAL / "lip_smear_zstack", REAL / "yeast_brightfield_zstack"
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
