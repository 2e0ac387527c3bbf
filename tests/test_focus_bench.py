"""`focustrack bench focus --quick`: runs end to end and writes the figures it targets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import focus, focus_real
from focustrack.cli import main


def test_quick_bench_writes_every_figure_per_metric(tmp_path: Path, capsys) -> None:
    parser = argparse.ArgumentParser()
    focus.add_arguments(parser)
    out = tmp_path / "focus.json"
    args = parser.parse_args(["--quick", "--metrics", "normalised_variance", "--json", str(out)])
    assert focus.run(args) == 0
    figures = json.loads(out.read_text())
    assert figures["source"] == "instrument_sim"
    row = figures["metrics"]["normalised_variance"]
    for key in ("fps_2048_u16", "fps_1024_rgb", "copy_ratio", "mae_um", "p90_um", "zscore_std"):
        assert row[key] > 0, key
    assert row["empty_flat"] == 1.0  # every empty field is flagged, none measured
    assert set(row["by_field"]) == {f"{f} {s}px" for f in focus.SPECIMEN_FIELDS for s in (256, 128)}
    assert "accuracy on simulated stacks" in capsys.readouterr().out


def test_targets_leave_out_unusable_measures_and_say_what_they_meet() -> None:
    good = {"within_1_step": 1.0, "coverage_2sigma": 1.0, "silent_miss": 0.0}
    good_windows = good | {"edge_right": 1.0, "edge_wrong": 0.0}
    flat = {"within_1_step": np.nan, "coverage_2sigma": np.nan, "silent_miss": 0.0}
    figures = {
        "BRENNER": {
            "full": good,
            "windows": good_windows,
            "windows_11x3": {"median_sigma_steps": 0.1},
        },
        "VOLLATH_F4": {
            "full": flat,
            "windows": flat | {"edge_right": 0.0, "edge_wrong": 0.0},
            "windows_11x3": {"median_sigma_steps": np.nan},
        },
    }
    assert all(misses == [] for misses in focus_real.targets(figures, {"VOLLATH_F4"}).values())
    assert "VOLLATH_F4" in focus_real.targets(figures)["coverage_2sigma >= 92%"]
    verdict = focus_real.unusable_targets(figures, {"VOLLATH_F4"})["VOLLATH_F4"]
    assert verdict["met"] == ["edge flags wrong <= 0.5%", "silent misses <= 1 in 1000"]
    assert "edge flags right >= 98%" in verdict["not_met"]


@pytest.mark.skipif(not focus.REAL_DIR.is_dir(), reason=f"{focus.REAL_DIR} is missing")
@pytest.mark.slow  # about a minute
def test_calibrate_on_even_fields_then_the_odd_ones_meet_every_target(tmp_path: Path) -> None:
    """The harder way round: the even fields calibrate, the odd ones (field 5 and its
    one-frame dip among them) are read. A gradient measure and normalized variance meet
    every target with the profile (coverage on 11x3 windows, edge flags, confident-wrong
    at most 0.1 %) and with none (coverage 85 %, confident-wrong 0.2 %)."""
    metrics = ["BRENNER", "NORMALIZED_VARIANCE"]
    result = focus_real.calibrate_and_hold_out(focus.REAL_DIR, "even", metrics, tmp_path, 2)
    assert result["held_out"] == "odd" and result["unusable"] == []
    assert all(misses == [] for misses in result["targets"].values()), result["targets"]
    assert all(misses == [] for misses in result["no_profile_targets"].values()), result[
        "no_profile_targets"
    ]
    for metric in metrics:
        assert result["with_profile"][metric]["windows"]["silent_miss"] <= 0.001, metric


@pytest.mark.skipif(not focus.REAL_DIR.is_dir(), reason=f"{focus.REAL_DIR} is missing")
def test_vollath_faint_bump_on_field_10_is_no_confident_miss_without_a_profile() -> None:
    """WSI field 10's VOLLATH_F4, read with no profile (a metric the service knows nothing
    of): five windows read its faint bump 3.4-16 steps from the label with a noise estimate
    from a few third differences, confidently, before that estimate was bounded
    (`noise_bound`); none now."""
    fields = [f for f in focus_real.half_fields(focus.REAL_DIR, "even") if f.number == 10]
    figures = focus_real.read_without_profile(fields, ["VOLLATH_F4"])["VOLLATH_F4"]
    assert figures["windows"]["n_inside"] > 0 and figures["windows"]["measured"] > 0.1
    assert figures["windows"]["silent_miss"] == 0.0


@pytest.mark.skipif(not focus.REAL_DIR.is_dir(), reason=f"{focus.REAL_DIR} is missing")
@pytest.mark.slow  # about 30 s on the loaded 2-core machine
def test_calibrate_on_none_reads_each_half_with_no_profile_alone(tmp_path: Path) -> None:
    """`--real --calibrate-on none`: no command run, each half read as curves labelled with
    the measures' names and no profile (here one field of each half): the figures and the
    no-profile targets that `--calibrate-on both` prints in its "none" columns."""
    real_dir = tmp_path / "real"
    (real_dir / "wsi_focus_curves").mkdir(parents=True)
    for number in (9, 10):
        name = f"group{number:02d}.json"
        (real_dir / "wsi_focus_curves" / name).symlink_to(
            focus.REAL_DIR / "wsi_focus_curves" / name
        )
    parser = argparse.ArgumentParser()
    focus.add_arguments(parser)
    out = tmp_path / "none.json"
    argv = ["--real", "--calibrate-on", "none", "--real-dir", str(real_dir), "--json", str(out)]
    assert focus.run(parser.parse_args(argv)) == 0
    runs = json.loads(out.read_text())["runs"]
    assert [run["held_out"] for run in runs] == ["odd", "even"]
    for run in runs:
        assert set(run["no_profile"]) == set(focus_real.HOLDOUT_METRICS)
        assert set(run["no_profile_targets"]) == {t[0] for t in focus_real.NO_PROFILE_TARGETS}
        assert run["no_profile"]["BRENNER"]["windows"]["n_inside"] > 0


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make a bench that starts its work by mistake (an argument not refused) fail at once
    rather than run for minutes."""

    def work(*_: object, **__: object) -> None:
        raise AssertionError("the bench began its work")

    monkeypatch.setattr(focus, "simulate", work)
    monkeypatch.setattr(focus_real.calibration, "calibrate", work)
    monkeypatch.setattr(focus_real, "calibrate_and_hold_out", work)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seed", "-1", "--quick"], "argument --seed: must be in [0, 4294967295], got -1"),
        (["--real", "--real-dir", "/nonexistent"], "argument --real-dir: /nonexistent is not"),
        (
            ["--real", "--calibrate-on", "odd", "--folds", "1"],
            "argument --folds: must be at least 2, got 1",
        ),
        (["--metrics"], "argument --metrics: expected at least one argument"),
    ],
)
def test_a_bad_value_is_refused_before_any_work(
    argv: list[str], message: str, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each was a traceback, a status of 1 or a calibration failing after the work began."""
    with pytest.raises(SystemExit) as stopped:
        main(["bench", "focus", *argv])
    assert stopped.value.code == 2
    assert f"focustrack bench focus: error: {message}" in capsys.readouterr().err


def test_calibrate_on_without_real_is_refused(
    no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """It was ignored, and the simulator's bench run instead."""
    assert main(["bench", "focus", "--quick", "--calibrate-on", "odd"]) == 2
    assert "focustrack bench focus: error: --calibrate-on needs --real" in capsys.readouterr().err


def test_real_without_the_curves_folder_is_refused(
    tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """A --real-dir that is there but holds no wsi_focus_curves: status 2 (it was 1)."""
    assert main(["bench", "focus", "--real", "--real-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "focustrack bench focus: error: --real needs" in err and "wsi_focus_curves" in err


def test_figures_with_nothing_measured_are_written_as_null(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A measure that measured nothing has NaN figures: the bench's JSON holds them as null
    (it held a bare NaN, which JSON.parse refuses)."""
    keys = [key for key, _, _ in focus_real._COLUMNS]
    keys += [key for _, _, key, _, _ in focus_real.NO_PROFILE_TARGETS]
    nothing = {part: dict.fromkeys(keys, np.nan) for part in ("full", "windows", "windows_11x3")}
    monkeypatch.setattr(focus_real, "half_fields", lambda *_: [])
    monkeypatch.setattr(
        focus_real, "read_without_profile", lambda _, metrics: dict.fromkeys(metrics, nothing)
    )
    (tmp_path / "real" / "wsi_focus_curves").mkdir(parents=True)
    out = tmp_path / "none.json"
    argv = ["--real", "--calibrate-on", "none", "--real-dir", str(tmp_path / "real")]
    assert main(["bench", "focus", *argv, "--json", str(out)]) == 0

    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} in the JSON")

    runs = json.loads(out.read_text(), parse_constant=refuse)["runs"]
    assert runs[0]["no_profile"]["BRENNER"]["windows"]["edge_right"] is None
