"""A curve of a metric the service has no entry for: an offset of a quarter of the depth of
field in its sigma, and the broad-top rule on windows of every length (`unprofiled`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from focustrack_core.domain import FocusFlag
from focustrack_focus.app import create_app
from focustrack_focus.calibration import parts, read_fields
from focustrack_focus.curve_checks import uniform_sigma_um
from focustrack_focus.labelled_curves import wsi_curves
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings, focus_from_curve
from focustrack_focus.profile import MetricProfile, MicroscopeProfile
from focustrack_focus.real_data import load_wsi_fields
from focustrack_focus.unprofiled import settings_without_entry, unprofiled

WSI = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real" / "wsi_focus_curves"
Z_UM = np.arange(0.0, 5.5, 0.5)  # 11 frames, 0.5 um apart
PEAK = 100.0 + 900.0 * np.exp(-0.5 * ((Z_UM - 2.6) / 1.0) ** 2)


def test_only_a_metric_the_service_does_not_know_is_read_as_unprofiled() -> None:
    base = FocusSettings()
    for metric in METRICS:
        assert settings_without_entry(metric, base) == base
    unknown = settings_without_entry("JPEG", base).peak
    # a quarter of the depth of field: half of the optics' narrowest peak's std
    assert unknown.systematic_sigma_um == pytest.approx(0.5 * base.peak.min_peak_sigma_um)
    assert unknown.broad_top_exempt_frames == 0
    # a larger systematic sigma set for the service stays
    assert unprofiled(PeakSettings(systematic_sigma_um=0.4)).systematic_sigma_um == 0.4
    # a profile's entry reads its metric, whatever the service knows of it
    profile = MicroscopeProfile({"JPEG": MetricProfile(0.001, 0.05)})
    assert profile.settings_for("JPEG", base).peak.systematic_sigma_um == 0.05


def test_the_curve_endpoint_widens_the_sigma_of_an_unknown_metrics_peak() -> None:
    """The same clean peak, labelled with one of the service's metrics and with a name it
    does not know: the same z, and for the latter a sigma of at least a quarter of the
    depth of field (the metric's own offset from focus is unknown)."""
    client = TestClient(create_app(FocusSettings()))

    def read(metric: str) -> dict:
        body = {"z_um": Z_UM.tolist(), "scores": PEAK.tolist(), "metric": metric}
        reply = client.post("/v1/focus/curve", json=body)
        assert reply.status_code == 200, reply.text
        return reply.json()

    known, unknown = read("brenner"), read("SOMEONE_ELSES_METRIC")
    assert known["flags"] == unknown["flags"] == []
    assert unknown["best_z_um"] == pytest.approx(known["best_z_um"]) == pytest.approx(2.6, abs=0.05)
    assert known["sigma_um"] < 0.05 and unknown["sigma_um"] >= 0.125


def test_a_short_window_on_a_broad_bump_of_an_unknown_metric_is_ambiguous() -> None:
    """Five frames on a gentle bump whose std is 1.5 times their span: a service metric's
    short stack keeps its exemption (placed around a confident prediction), a metric the
    service knows nothing of does not: ambiguous, a sigma of a focus anywhere in it."""
    z = np.arange(5.0)
    bump = 1.0 + np.exp(-0.5 * ((z - 2.2) / 6.0) ** 2)
    known = focus_from_curve(z, bump, FocusSettings())
    assert known.flags == frozenset() and known.sigma_um is not None
    unknown = focus_from_curve(z, bump, settings_without_entry("VOLLATH_F4", FocusSettings()))
    assert FocusFlag.AMBIGUOUS in unknown.flags and unknown.sigma_um is not None
    assert unknown.sigma_um >= uniform_sigma_um(4.0)


@pytest.mark.skipif(not WSI.is_dir(), reason=f"{WSI} is missing (see its README)")
@pytest.mark.slow  # about 10 s
def test_jpeg_and_vollath_on_the_odd_wsi_fields_without_a_profile() -> None:
    """The odd WSI fields read as curves labelled JPEG and VOLLATH_F4 with no profile (the
    service has no entry for either): JPEG's peak sits about a step from the label on most
    fields, and its 11x3 coverage reaches 85 % (69 % when read as a service metric); Vollath
    F4's faint bump read in 5-frame windows is no longer confident-wrong (0.70 % before)."""
    fields = wsi_curves([f for f in load_wsi_fields(WSI) if f.number % 2 == 1])
    empty = MicroscopeProfile({})
    jpeg = parts(read_fields(fields, "JPEG", empty.settings_for("JPEG", FocusSettings())))
    assert jpeg["windows_11x3"]["coverage_2sigma"] >= 0.85
    assert jpeg["windows"]["silent_miss"] <= 0.002
    vollath = read_fields(fields, "VOLLATH_F4", empty.settings_for("VOLLATH_F4", FocusSettings()))
    assert parts(vollath)["windows"]["silent_miss"] <= 0.002
