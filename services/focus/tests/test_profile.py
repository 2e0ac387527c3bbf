"""Labelled curves in the JSONL form, microscope profiles, and the REST app reading a curve
with the entry its metric label names."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from focustrack_focus.app import create_app
from focustrack_focus.labelled_curves import (
    CurvesFileError,
    LabelledCurve,
    load_curves,
    write_curves,
)
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.profile import MetricProfile, MicroscopeProfile, ProfileError
from focustrack_focus.service import main

Z_UM = np.arange(0.0, 10.01, 0.5)
PEAK = 100.0 + 1000.0 * np.exp(-0.5 * ((Z_UM - 4.2) / 1.5) ** 2)


def test_curves_round_trip_through_the_jsonl_form(tmp_path: Path) -> None:
    curve = LabelledCurve(7, Z_UM, {"BRENNER": PEAK, "JPEG": PEAK[::-1].copy()}, 4.0)
    path = tmp_path / "curves.jsonl"
    write_curves(path, [curve, LabelledCurve(8, Z_UM, {"BRENNER": PEAK}, 4.5)])
    first, second = load_curves(path)
    assert first.number == 7 and second.number == 8 and first.focus_z_um == 4.0
    assert np.array_equal(first.scores["JPEG"], PEAK[::-1]) and first.label_index == 8
    assert first.step_um == 0.5
    # without "field" a line is numbered by its place; z may come in any order
    lines = [{"z_um": Z_UM[::-1].tolist(), "scores": {"B": PEAK[::-1].tolist()}, "focus_z_um": 4}]
    path.write_text("\n" + "\n".join(json.dumps(line) for line in lines) + "\n")
    (only,) = load_curves(path)
    assert only.number == 2 and np.array_equal(only.z_um, Z_UM)
    assert np.array_equal(only.scores["B"], PEAK)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("{not json", "line 1: not JSON"),
        ('{"z_um": [0, 1, 2], "scores": {"B": [1, 2, 3]}}', "line 1: missing focus_z_um"),
        ('{"z_um": [0, 1, 2], "scores": {"B": [1, 2]}, "focus_z_um": 1}', "line 1: 3 z values"),
        ('{"z_um": [0, 1, 2], "scores": {}, "focus_z_um": 1}', '"scores" must be an object'),
        ('{"z_um": [0, 1, 2], "scores": {"B": [1, 2, 3]}, "focus_z_um": 9}', "outside the"),
        ('{"z_um": [0, 1, 1], "scores": {"B": [1, 2, 3]}, "focus_z_um": 1}', "distinct"),
        ('{"z_um": [0, 1, 2], "scores": {"B": [1, 2, 3]}, "focus_z_um": true}', "finite"),
        ("[1, 2]", "line 1: a field is a JSON object"),
        # numpy read these as numbers
        ('{"z_um": ["0", "1", "2"], "scores": {"B": [1, 2, 3]}, "focus_z_um": 1}', 'z_um" must'),
        ('{"z_um": [0, 1, 2], "scores": {"B": [1, true, 3]}, "focus_z_um": 1}', "'B' scores must"),
        ('{"z_um": 5, "scores": {"B": [1, 2, 3]}, "focus_z_um": 1}', "must be a list of numbers"),
        ('{"z_um": [0, 1, 2], "scores": {"%s": [1, 2, 3]}, "focus_z_um": 1}' % ("M" * 65), "64"),
        ('{"z_um": [0, 1, 2], "scores": {"": [1, 2, 3]}, "focus_z_um": 1}', "not empty"),
    ],
)
def test_a_bad_line_is_refused_with_its_number(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "bad.jsonl"
    path.write_text(line + "\n")
    with pytest.raises(CurvesFileError, match=message):
        load_curves(path)


@pytest.mark.parametrize(
    "content", [b"\x89PNG\r\n\x1a\n\x00\x00", '{"z_um": [0, 1, 2]}\n'.encode("utf-16")]
)
def test_a_file_that_is_not_utf8_text_is_refused_naming_it(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "curves.png"
    path.write_bytes(content)  # was a UnicodeDecodeError
    with pytest.raises(CurvesFileError, match=f"{path}: not UTF-8 text"):
        load_curves(path)


def test_a_field_named_twice_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "twice.jsonl"
    write_curves(path, [LabelledCurve(3, Z_UM, {"B": PEAK}, 4.0)] * 2)
    with pytest.raises(CurvesFileError, match="appears twice"):
        load_curves(path)


def test_a_profile_round_trips_and_a_bad_one_says_why(tmp_path: Path) -> None:
    profile = MicroscopeProfile(
        {"BRENNER": MetricProfile(0.0002, 0.1, curve_fwhm_um=4.4, coarse_step_um=3.6)}, "x"
    )
    path = tmp_path / "profile.json"
    profile.save(path)
    assert MicroscopeProfile.load(path) == profile
    path.write_text(json.dumps({"version": 2, "metrics": {}}))
    with pytest.raises(ProfileError, match="version 2"):
        MicroscopeProfile.load(path)
    path.write_text(json.dumps({"version": 1, "metrics": {"B": {"relative_noise": -1}}}))
    with pytest.raises(ProfileError, match="metric 'B'"):
        MicroscopeProfile.load(path)
    with pytest.raises(ProfileError, match="cannot read"):
        MicroscopeProfile.load(tmp_path / "missing.json")


GOOD_ENTRY = {"relative_noise": 0.001, "systematic_sigma_um": 0.1, "curve_fwhm_um": 4.4}


@pytest.mark.parametrize(
    ("field", "value", "needle"),
    [
        ("curve_fwhm_um", "wide", "curve_fwhm_um (um, or null) must be a number in (0, 2e+06]"),
        ("curve_fwhm_um", float("nan"), "curve_fwhm_um"),
        ("curve_fwhm_um", -4, "curve_fwhm_um"),
        ("curve_fwhm_um", 0, "curve_fwhm_um"),
        ("coarse_step_um", 0.0, "coarse_step_um"),
        ("systematic_sigma_um", 1e308, "systematic_sigma_um (um) must be a number in [0, 1000]"),
        ("systematic_sigma_um", True, "got True"),
        ("relative_noise", False, "relative_noise"),
        ("unusable_because", None, 'unusable_because must be a string ("" when usable)'),
        ("unusable_because", 5, "got 5"),
        ("cross_validation", [], "cross_validation must be an object"),
    ],
)
def test_a_profile_value_the_maths_cannot_take_is_refused_naming_metric_and_field(
    tmp_path: Path, field: str, value: object, needle: str
) -> None:
    """Each of these was loaded, then made every curve of the metric a 500."""
    path = tmp_path / "profile.json"
    path.write_text(json.dumps({"version": 1, "metrics": {"BRENNER": GOOD_ENTRY | {field: value}}}))
    with pytest.raises(ProfileError, match=re.escape(f"{path}: metric 'BRENNER': ")) as refused:
        MicroscopeProfile.load(path)
    assert needle in str(refused.value)


def test_the_curve_endpoint_reads_a_curve_with_its_metric_labels_entry() -> None:
    profile = MicroscopeProfile(
        {
            "BLIND": MetricProfile(0.0, 0.0, unusable_because="all flat on the fit fields"),
            "OFFSET": MetricProfile(0.0, 0.4),
        }
    )
    client = TestClient(create_app(FocusSettings(), profile=profile))

    def read(metric: str) -> dict:
        body = {"z_um": Z_UM.tolist(), "scores": PEAK.tolist(), "metric": metric}
        reply = client.post("/v1/focus/curve", json=body)
        assert reply.status_code == 200, reply.text
        return reply.json()

    plain, blind, offset = read("OTHER"), read("BLIND"), read("OFFSET")
    assert plain["flags"] == [] and abs(plain["best_z_um"] - 4.2) < 0.05
    assert blind["flags"] == ["flat"] and blind["best_z_um"] is None
    assert offset["metric"] == "OFFSET" and offset["sigma_um"] >= 0.4 > plain["sigma_um"]


def test_serve_focus_refuses_a_profile_it_cannot_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "profile.json"
    bad.write_text("{")
    assert main(["--profile", str(bad)]) == 2
    assert "is not JSON" in capsys.readouterr().err
    bad.write_bytes(b"\x89PNG\r\n\x1a\n")  # was "'utf-8' codec can't decode byte 0x89 ..."
    assert main(["--profile", str(bad)]) == 2
    assert f"the profile {bad} is not UTF-8 text" in capsys.readouterr().err
    entry = GOOD_ENTRY | {"systematic_sigma_um": 1e308}  # was a 500 on every BRENNER curve
    bad.write_text(json.dumps({"version": 1, "metrics": {"BRENNER": entry}}))
    assert main(["--profile", str(bad)]) == 2
    assert "metric 'BRENNER': systematic_sigma_um" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "message"), [("M" * 65, "at most 64 characters"), ("", "not empty")]
)
def test_a_profile_of_a_metric_name_no_label_can_give_is_refused(
    tmp_path: Path, name: str, message: str
) -> None:
    path = tmp_path / "profile.json"
    path.write_text(json.dumps({"version": 1, "metrics": {name: GOOD_ENTRY}}))
    with pytest.raises(ProfileError, match=message):
        MicroscopeProfile.load(path)
