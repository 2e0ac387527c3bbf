"""`focustrack bench accuracy` end to end through the CLI: generated maps and a user's files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import strategies as registry
from focustrack.bench.accuracy import ELSEWHERE
from focustrack.cli import main
from focustrack_core.surfaces import Outliers, add_outliers, family_spec, generate_surfaces

REQUIRED = [
    "kf-wiener0",
    "kf-wiener1",
    "kf-wiener2",
    "kf-gm1",
    "kf-gm2",
    "kf-wiener1-dir",
    "kf-mmae",
    "af-every-tile",
    "tile-skip",
    "survey-bilinear",
    "survey-spline",
    "survey-delaunay",
]
FIELDS = {
    "prior_mae_um",
    "prior_std_um",
    "post_mae_um",
    "post_std_um",
    "images_per_tile",
    "scan_time_s",
    "in_focus_fraction",
    "limit_time_s",
    "frames_kept_per_tile",
}


def _bench(*args: str | Path) -> int:
    return main(["bench", "accuracy", "--no-progress", *map(str, args)])


def test_generated_maps_json_table_and_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "accuracy.json"
    assert _bench("--maps", 2, "--size", 10, "--seed", 3, "--json", out, "--plots", tmp_path) == 0
    report = json.loads(out.read_text())
    strategies = report["strategies"]
    smoothed = {name for name in strategies if name.endswith("-rts")}
    assert set(REQUIRED) <= set(strategies)
    assert set(strategies) - smoothed == set(registry.STRATEGIES) - ELSEWHERE
    # Every 1-D Kalman strategy fills the smoothed layers: a -rts row each.
    assert {f"{name}-rts" for name in REQUIRED if name.startswith("kf-")} <= smoothed
    for name, fields in strategies.items():
        assert set(fields) == FIELDS, name
        assert fields["post_mae_um"] > 0 and 0 <= fields["in_focus_fraction"] <= 1
        assert fields["images_per_tile"] >= 1 and fields["scan_time_s"] > 0
        has_prior = not name.startswith(("af-", "tile-", "survey-"))
        assert (fields["prior_mae_um"] is not None) == has_prior, name
        assert (fields["prior_std_um"] is not None) == has_prior, name
    for name in smoothed:  # the same scan: only the final map differs
        filtered = strategies[name.removesuffix("-rts")]
        for field in ("prior_mae_um", "images_per_tile", "scan_time_s", "in_focus_fraction"):
            assert strategies[name][field] == filtered[field], (name, field)
        assert strategies[name]["post_mae_um"] != filtered["post_mae_um"]
    assert strategies["af-every-tile"]["images_per_tile"] == 41.0
    assert report["families"]["standard"]["strategies"] == strategies
    # the lean strategy states its risk, and its reliability table covers every tile
    bins = report["families"]["standard"]["reliability"]["kf-2d-lean"]
    assert sum(b["n_tiles"] for b in bins) == 2 * 10 * 10
    assert set(report["families"]["standard"]["reliability"]) == {"kf-2d-lean"}

    printed = capsys.readouterr().out
    assert "standard: 2 maps of 10x10, seed 3" in printed
    assert all(name in printed for name in REQUIRED)
    assert "kf-wiener0-rts" in printed and "RTS-smoothed" in printed
    assert "kf-2d-lean: stated risk 1.0%" in printed and "/ limit" in printed
    assert (tmp_path / "errors_standard.png").stat().st_size > 0
    assert (tmp_path / "summary_standard.png").stat().st_size > 0


def test_families_are_reported_apart(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "accuracy.json"
    args = ["--maps", 2, "--size", 8, "--family", "standard", "--family", "steps"]
    assert _bench(*args, "--strategies", "af-every-tile,tile-skip", "--json", out) == 0
    report = json.loads(out.read_text())
    assert set(report["families"]) == {"standard", "steps"}
    assert set(report["strategies"]) == {"af-every-tile", "tile-skip"}
    printed = capsys.readouterr().out
    assert "standard: 2 maps of 8x8" in printed and "steps: 2 maps of 8x8" in printed


def test_several_families_after_one_flag_with_outliers_and_oracle_ratios(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "accuracy.json"
    args = ["--maps", 2, "--size", 8, "--family", "standard", "outliers", "--json", out]
    names = ["kf-wiener0", "gp-oracle"] if "gp-oracle" in registry.STRATEGIES else ["kf-wiener0"]
    assert _bench(*args, "--strategies", *names) == 0
    families = json.loads(out.read_text())["families"]
    assert set(families) == {"standard", "outliers"}
    standard = families["standard"]["strategies"]["kf-wiener0"]
    outliers = families["outliers"]["strategies"]["kf-wiener0"]
    assert outliers["prior_mae_um"] > standard["prior_mae_um"]  # same surfaces, worse data
    printed = capsys.readouterr().out
    assert ("prior/oracle" in printed) == ("gp-oracle" in names)


def test_a_stated_risk_below_the_oracles_is_called_unattainable(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """At the thesis noise (1.5 um) even the Bayes-optimal oracle leaves about a third of
    tiles out of focus with one frame per tile: the bench says so beside the lean rule's
    frames kept per tile."""
    args = ["--maps", 2, "--size", 8, "--strategies", "kf-2d-lean", "gp-oracle"]
    assert _bench(*args) == 0
    printed = capsys.readouterr().out
    assert "kf-2d-lean: stated risk 1.0%" in printed
    assert "one frame per tile could not meet the stated 1.0% here: gp-oracle" in printed
    assert "frames kept per tile: " in printed
    assert _bench(*args[:4], "--noise-um", 0.1, *args[4:]) == 0
    assert "could not meet" not in capsys.readouterr().out


def test_outliers_hit_about_the_given_fraction_of_tiles() -> None:
    measured = np.zeros((4, 20, 20))
    corrupted = add_outliers(measured, Outliers(0.05, 3.0, 8.0), seed=1)
    hit = np.abs(corrupted) > 0
    assert 0.03 < hit.mean() < 0.07
    assert np.all((np.abs(corrupted[hit]) >= 3.0) & (np.abs(corrupted[hit]) <= 8.0))
    assert np.array_equal(corrupted, add_outliers(measured, Outliers(0.05, 3.0, 8.0), seed=1))


def test_a_users_truth_and_measured_maps_are_replayed_as_given(tmp_path: Path) -> None:
    # Absolute stage heights: the scan starts at the first tile's measured focus.
    truth = 2000.0 + generate_surfaces(family_spec("standard", 6, 7), 1, seed=4)[0]
    measured = truth + np.random.default_rng(4).normal(0.0, 1.0, truth.shape)
    np.save(tmp_path / "truth.npy", truth)
    np.savetxt(tmp_path / "measured.csv", measured, delimiter=",")
    out = tmp_path / "user.json"
    args = ["--truth-map", tmp_path / "truth.npy", "--measured-map", tmp_path / "measured.csv"]
    assert _bench(*args, "--noise-um", 1.0, "--json", out) == 0
    strategies = json.loads(out.read_text())["strategies"]
    af = strategies["af-every-tile"]
    # Autofocus on every tile images each tile at its measurement: its error is the noise.
    assert af["post_mae_um"] == pytest.approx(np.mean(np.abs(measured - truth)), abs=1e-9)
    assert af["images_per_tile"] == 41.0
    assert strategies["kf-wiener0"]["post_mae_um"] < 2.0


def test_a_users_map_stack_with_simulated_noise(tmp_path: Path) -> None:
    truth = generate_surfaces(family_spec("standard", 6, 6), 2, seed=9)
    np.save(tmp_path / "stack.npy", truth)
    out_a, out_b = tmp_path / "a.json", tmp_path / "b.json"
    args = ["--truth-map", tmp_path / "stack.npy", "--noise-um", 0.5, "--seed", 2]
    assert _bench(*args, "--strategies", "af-every-tile", "kf-wiener1", "--json", out_a) == 0
    assert _bench(*args, "--strategies", "af-every-tile", "kf-wiener1", "--json", out_b) == 0
    report = json.loads(out_a.read_text())
    assert report == json.loads(out_b.read_text())  # the seed fixes the noise
    assert report["families"]["user"]["maps"] == 2
    assert 0.2 < report["strategies"]["af-every-tile"]["post_mae_um"] < 0.6


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--measured-map", "m.npy"], "--measured-map needs --truth-map"),
        (["--truth-map", "TRUTH", "--family", "steps"], "apply to generated maps"),
        (["--truth-map", "TRUTH", "--measured-map", "SMALL"], "has shape (1, 3, 3)"),
        (["--truth-map", "missing.npy"], "missing.npy"),
        (["--strategies", "kf-wiener9"], "unknown strategy kf-wiener9"),
        (["--size", "3", "--strategies", "survey-spline"], "at least 4 survey points per axis"),
        (["--truth-map", "TRUTH", "--strategies", "gp-oracle"], "needs generated maps"),
    ],
)
def test_bad_input_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    np.save(tmp_path / "truth.npy", np.zeros((4, 4)))
    np.save(tmp_path / "small.npy", np.zeros((3, 3)))
    paths = {"TRUTH": tmp_path / "truth.npy", "SMALL": tmp_path / "small.npy"}
    assert _bench(*[paths.get(a, a) for a in args]) == 2
    assert message in capsys.readouterr().err
