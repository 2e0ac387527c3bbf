"""`focustrack focus calibrate` as a user runs it, and `bench focus --real --calibrate-on`'s
loop on the shared WSI curves (a tiny version)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import focus_real
from focustrack.bench.focus import REAL_DIR
from focustrack.cli import main
from focustrack_focus.labelled_curves import LabelledCurve, write_curves
from focustrack_focus.profile import MicroscopeProfile

needs_real = pytest.mark.skipif(not REAL_DIR.is_dir(), reason=f"{REAL_DIR} is missing")


def biased_curves(n_fields: int, bias_steps: float, seed: int) -> list[LabelledCurve]:
    """Fields of a metric whose peak lies `bias_steps` either way of the labelled focus at
    random (a metric that weighs other frequencies than the eye), 0.5 um steps."""
    rng = np.random.default_rng(seed)
    z_um = 0.5 * np.arange(60)
    curves = []
    for number in range(1, n_fields + 1):
        focus = float(rng.uniform(10.0, 20.0))
        peak = focus + 0.5 * bias_steps * rng.choice([-1.0, 1.0])
        scores = 50.0 + 1000.0 * np.exp(-0.5 * ((z_um - peak) / 1.8) ** 2)
        scores += rng.normal(0.0, 0.2, z_um.size)
        curves.append(LabelledCurve(number, z_um, {"M": scores, "CLEAN": scores}, focus))
    return curves


def test_calibrate_learns_a_systematic_sigma_and_writes_the_profile_and_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    curves = tmp_path / "curves.jsonl"
    write_curves(curves, biased_curves(8, 1.0, 3))
    out = tmp_path / "scope.json"
    argv = ["focus", "calibrate", "--curves", str(curves), "--out", str(out), "--folds", "4"]
    assert main([*argv, "--metrics", "M"]) == 0
    printed = capsys.readouterr().out
    assert "4-fold cross-validation" in printed and printed.count("\n  ") >= 5  # the folds
    entry = MicroscopeProfile.load(out).metrics["M"]
    # a step (0.5 um) off either way: |e| <= 2 hypot(sigma, s) + half a step needs s >= ~0.12 um
    assert entry.usable and 0.1 <= entry.systematic_sigma_um <= 0.2
    assert entry.curve_fwhm_um == pytest.approx(2.355 * 1.8, rel=0.1)
    assert entry.coarse_step_um is not None and entry.coarse_step_um <= entry.curve_fwhm_um
    folds = entry.cross_validation["folds"]
    assert len(folds) == 4 and sum(len(f["held_out"]) for f in folds) == 8
    assert out.with_suffix(".png").stat().st_size > 10_000
    json.loads(out.read_text())  # plain JSON: no NaN


def test_calibrate_refuses_bad_input_with_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    curves = tmp_path / "curves.jsonl"
    curves.write_text('{"z_um": [0, 1], "scores": {"M": [1, 2]}, "focus_z_um": 0}\n')
    out = tmp_path / "p.json"
    assert main(["focus", "calibrate", "--curves", str(curves), "--out", str(out)]) == 2
    assert "line 1" in capsys.readouterr().err and not out.exists()
    write_curves(curves, biased_curves(3, 0.0, 1))
    assert main(["focus", "calibrate", "--curves", str(curves), "--out", str(out)]) == 2
    assert "--folds must be 2 .. 3" in capsys.readouterr().err
    argv = ["focus", "calibrate", "--curves", str(curves), "--out", str(out), "--folds", "3"]
    assert main([*argv, "--metrics", "NOPE"]) == 2


def test_calibrate_leaves_out_a_field_whose_scores_of_a_metric_are_all_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A metric that sees nothing in a field cannot be calibrated there: the field is left
    out of that metric, with a line saying so (it was a traceback, exit 1)."""
    fields = biased_curves(6, 0.5, 2)
    blank = fields[2]
    scores = {"M": np.zeros(blank.z_um.size), "CLEAN": blank.scores["CLEAN"]}
    fields[2] = LabelledCurve(blank.number, blank.z_um, scores, blank.focus_z_um)
    curves, out = tmp_path / "curves.jsonl", tmp_path / "scope.json"
    write_curves(curves, fields)
    argv = ["focus", "calibrate", "--curves", str(curves), "--out", str(out), "--folds", "2"]
    assert main(argv) == 0
    assert "M: field 3 left out, every score 0 or below there" in capsys.readouterr().out
    profile = MicroscopeProfile.load(out)

    def held_out(metric: str) -> list[int]:
        folds = profile.metrics[metric].cross_validation["folds"]
        return sorted(field for fold in folds for field in fold["held_out"])

    assert held_out("M") == [1, 2, 4, 5, 6] and held_out("CLEAN") == [1, 2, 3, 4, 5, 6]
    # too few fields left for the folds: refused up front, naming the metric and fields
    for field in fields[1:]:
        field.scores["M"][:] = 0.0
    write_curves(curves, fields)
    assert main(argv) == 2
    assert "M scores above 0 in only 1 of the 6 fields (fields 2, 3, 4, 5, 6" in (
        capsys.readouterr().err
    )


@pytest.mark.parametrize(
    ("content", "message"),
    [
        # each was a traceback (exit 1) or a message that did not say what was wrong
        (b"\x89PNG\r\n\x1a\n\x00\x00", "curves.jsonl: not UTF-8 text"),
        ('{"z_um": [0, 1, 2]}'.encode("utf-16"), "curves.jsonl: not UTF-8 text"),
        (b'{"z_um": [0, 1, 2], "scores": {"M": [1, 2, 1]}, "focus_z_um": 1}',
         "curves.jsonl has only 1 field: cross-validation over fields needs at least 2"),
        (b'{"z_um": ["0", "1", "2"], "scores": {"M": [1, 2, 1]}, "focus_z_um": 1}',
         'line 1: "z_um" must be numbers, got \'0\''),
    ],
)  # fmt: skip
def test_calibrate_says_what_is_wrong_with_a_curves_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, message: str
) -> None:
    curves = tmp_path / "curves.jsonl"
    curves.write_bytes(content)
    out = tmp_path / "p.json"
    assert main(["focus", "calibrate", "--curves", str(curves), "--out", str(out)]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_calibrate_names_the_fields_a_metric_is_missing_from(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fields = biased_curves(4, 0.0, 1)
    del fields[1].scores["M"]
    curves, out = tmp_path / "curves.jsonl", tmp_path / "p.json"
    write_curves(curves, fields)
    argv = ["focus", "calibrate", "--curves", str(curves), "--out", str(out), "--folds", "2"]
    assert main([*argv, "--metrics", "M"]) == 2  # was "not every field has M"
    assert f"{curves}: no M scores in field 2" in capsys.readouterr().err
    assert main(argv) == 0  # every metric given: M is left out, with a line saying so
    assert "M left out: no M scores in field 2" in capsys.readouterr().out
    assert set(MicroscopeProfile.load(out).metrics) == {"CLEAN"}


@needs_real
def test_calibrate_on_odd_fields_then_hold_out_the_even_ones(tmp_path: Path) -> None:
    """The bench's loop, tiny: the command on the odd fields' BRENNER curves, the even fields
    read with the profile it wrote (and without one), against the targets."""
    result = focus_real.calibrate_and_hold_out(REAL_DIR, "odd", ["BRENNER"], tmp_path, 2)
    assert result["held_out"] == "even" and result["unusable"] == []
    assert (tmp_path / "odd.jsonl").read_text().count("\n") == 10
    with_profile = result["with_profile"]["BRENNER"]
    assert with_profile["windows_11x3"]["n_inside"] > 100
    assert all(misses == [] for misses in result["targets"].values()), result["targets"]
    assert all(misses == [] for misses in result["no_profile_targets"].values())


def test_calibrate_from_stacks_and_their_labels_file(tmp_path: Path) -> None:
    """`--stacks DIR`: .npy stacks scored with the service's metric, labels from labels.json."""
    import cv2

    z_um = np.arange(-4.0, 4.01, 0.5)
    labels = {}
    for number in range(3):
        rng = np.random.default_rng(number)
        texture = rng.uniform(0.0, 1000.0, (64, 64)).astype(np.float32)
        focus = float(rng.uniform(-1.0, 1.0))
        frames = [
            cv2.GaussianBlur(texture, (0, 0), 0.6 + 1.5 * abs(z - focus)) + 500.0 for z in z_um
        ]
        np.save(tmp_path / f"stack{number}.npy", np.array(frames).astype(np.uint16))
        labels[f"stack{number}.npy"] = {"z_um": z_um.tolist(), "focus_z_um": focus}
    (tmp_path / "labels.json").write_text(json.dumps(labels))
    out = tmp_path / "p.json"
    argv = ["focus", "calibrate", "--stacks", str(tmp_path), "--out", str(out), "--folds", "3"]
    assert main([*argv, "--metrics", "tenengrad"]) == 0
    entry = MicroscopeProfile.load(out).metrics["tenengrad"]
    assert entry.usable and entry.curve_fwhm_um is not None
    (tmp_path / "labels.json").write_text(json.dumps({"missing.npy": labels["stack0.npy"]}))
    assert main([*argv, "--metrics", "tenengrad"]) == 2


@needs_real
@pytest.mark.slow  # about 20 s
def test_the_bench_runs_the_loop_and_writes_its_figures_and_plot(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`focustrack bench focus --real --calibrate-on odd --json OUT`, on one measure."""
    monkeypatch.setattr(focus_real, "HOLDOUT_METRICS", ("BRENNER",))
    out = tmp_path / "holdout.json"
    argv = ["bench", "focus", "--real", "--calibrate-on", "odd", "--folds", "2"]
    assert main([*argv, "--json", str(out)]) == 0
    (run,) = json.loads(out.read_text())["runs"]
    assert run["calibrate_on"] == "odd" and set(run["with_profile"]) == {"BRENNER"}
    assert out.with_suffix(".png").is_file() and (tmp_path / "profile_odd.png").is_file()
    printed = capsys.readouterr().out
    assert "held-out even fields, profile learnt on the odd ones" in printed
    assert "targets with the profile" in printed and "targets with no profile" in printed
