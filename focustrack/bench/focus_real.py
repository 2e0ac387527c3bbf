"""`focustrack bench focus --real`: best z, sigma and flags on real through-focus curves.

Data: `wsi_focus_curves/` of ../shared/data/real (20 fields of a real
whole-slide-imaging microscope, hezhujun/autofocus-rnn; 100 positions 0.5 um
apart, 33 focus measures each, a best-focus index set by a person). Every curve,
full and in the windows a predictive scanner acquires, goes through
`focus_from_curve`, the path of POST /v1/focus/curve (`focustrack_focus.calibration`:
the windows, the figures, and each measure's constants on this microscope learnt
afresh on every run from the odd fields alone, a measure unusable there included).

Here: the measures reported, the figures printed and plotted, and the
targets on the even fields (2, 4, ..., 20), the headline figures. A measure found
unusable is reported as such, with its figures, instead of being counted against
targets that need a measurement (`targets`). With `--calibrate-on`, the whole loop a user
runs (`calibrate_and_hold_out`): the curves file of one half, `focustrack focus
calibrate` on it, the other half read with the profile it wrote and without one; with
`--calibrate-on none`, each half read with no profile alone (`run_without_profile`: the
"none" columns in about a minute, where the whole loop takes ten).
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from focustrack.arguments import refuse
from focustrack.bench.json_report import write_json
from focustrack_focus import calibration
from focustrack_focus.calibration import MEDIAN_SIGMA_TARGET_STEPS, parts, read_fields
from focustrack_focus.labelled_curves import LabelledCurve, write_curves, wsi_curves
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.profile import MicroscopeProfile
from focustrack_focus.real_data import WSI_STEP_UM, load_wsi_fields

#: The measures reported (the data set's names). Gradient ones carry the 97 % target.
GRADIENT_METRICS = ("BRENNER", "SQUARED_GRADIENT", "_3_3_SOBEL", "_5_5_SOBEL")
OTHER_METRICS = (
    "_3_3_LAPLACIAN",
    "LAPLACIAN_OF_GAUSSIAN",
    "NORMALIZED_VARIANCE",
    "VARIANCE",
    "VOLLATH_F4",
    "JPEG",
)
REAL_METRICS = GRADIENT_METRICS + OTHER_METRICS


_COLUMNS = (
    ("within_1_step", "<=1", "%"),
    ("within_2_steps", "<=2", "%"),
    ("coverage_2sigma", "2sig cov", "%"),
    ("median_sigma_steps", "med sig", "f"),
    ("multi_peak", "multi", "%"),
    ("ambiguous", "ambig", "%"),
    ("flat", "flat", "%"),
    ("edge_when_inside", "edge in", "%"),
    ("edge_right", "edge ok", "%"),
    ("edge_wrong", "edge bad", "%"),
    ("silent_miss", "silent", "%"),
)


def print_report(figures: dict[str, dict], title: str, unusable: Collection[str] = ()) -> None:
    """The figures as tables (full curves, windows, 11x3 windows); a metric declared unusable
    on the microscope is marked so (its coverage and sigma are nan: nothing measured)."""
    print(f"\n{title}")
    for part in ("full", "windows", "windows_11x3"):
        print(f"  {part}:")
        print(f"  {'metric':<24}" + "".join(f"{head:>10}" for _, head, _ in _COLUMNS))
        for metric, by_part in figures.items():
            row = by_part[part]
            cells = [
                f"{row[key]:>10.2%}" if kind == "%" else f"{row[key]:>10.2f}"
                for key, _, kind in _COLUMNS
            ]
            mark = "  unusable (all flat)" if metric in unusable else ""
            print(f"  {metric:<24}" + "".join(cells) + mark)


#: The targets: name -> (test on a measure's figures, gradient measures only).
#: Coverage and sigma count measured results only: a flat result carries no z and no
#: sigma, so it is neither covered nor a silent miss. The edge figures count every window
#: whose label lies outside, flat ones included (the targets' definition: how often the edge
#: flag points the right way and the wrong way), so a measure that never points anywhere
#: cannot meet "edge right".
_TARGETS: dict[str, tuple[Callable[[dict[str, dict]], bool], bool]] = {
    "within_1_step >= 97% (gradient metrics)": (
        lambda f: all(f[p]["within_1_step"] >= 0.97 for p in ("full", "windows")),
        True,
    ),
    "coverage_2sigma >= 92%": (
        lambda f: all(f[p]["coverage_2sigma"] >= 0.92 for p in ("full", "windows")),
        False,
    ),
    f"median sigma on 11x3 windows <= {MEDIAN_SIGMA_TARGET_STEPS} step": (
        lambda f: f["windows_11x3"]["median_sigma_steps"] <= MEDIAN_SIGMA_TARGET_STEPS,
        False,
    ),
    "edge flags right >= 98%": (lambda f: f["windows"]["edge_right"] >= 0.98, False),
    "edge flags wrong <= 0.5%": (lambda f: f["windows"]["edge_wrong"] <= 0.005, False),
    "silent misses <= 1 in 1000": (
        lambda f: all(f[p]["silent_miss"] <= 0.001 for p in ("full", "windows")),
        False,
    ),
}


def targets(figures: dict[str, dict], unusable: Collection[str] = ()) -> dict[str, list[str]]:
    """The targets on these figures: each target -> the metrics that miss it
    (an empty list: met by every metric it applies to). Metrics declared `unusable` on the
    microscope are left out: `unusable_targets` says what they meet."""
    usable = [m for m in figures if m not in unusable]
    return {
        name: [
            m for m in usable if (not gradient_only or m in GRADIENT_METRICS) and not ok(figures[m])
        ]
        for name, (ok, gradient_only) in _TARGETS.items()
    }


def unusable_targets(figures: dict[str, dict], unusable: Collection[str]) -> dict[str, dict]:
    """Per unusable metric: the targets it meets and those it does not (NaN, i.e. nothing
    measured, does not meet a target)."""
    out: dict[str, dict] = {}
    for metric in unusable:
        if metric not in figures:
            continue
        applies = [
            (name, ok)
            for name, (ok, gradient_only) in _TARGETS.items()
            if not gradient_only or metric in GRADIENT_METRICS
        ]
        out[metric] = {
            "met": [name for name, ok in applies if ok(figures[metric])],
            "not_met": [name for name, ok in applies if not ok(figures[metric])],
        }
    return out


def write_plot(path: Path, figures: dict[str, dict]) -> None:
    """A bar chart of the headline figures per metric (full curves and windows)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ("within_1_step", "coverage_2sigma", "edge_right", "edge_wrong", "silent_miss")
    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 4), sharey=True)
    names = list(figures)
    for ax, key in zip(axes, keys, strict=True):
        for offset, part in ((-0.2, "full"), (0.2, "windows")):
            values = [figures[m][part][key] for m in names]
            ax.barh(np.arange(len(names)) + offset, values, height=0.4, label=part)
        ax.set(title=key, xlim=(0, 1))
    axes[0].set_yticks(np.arange(len(names)), names, fontsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_wsi_curves(real_dir: Path, numbers: Collection[int], path: Path) -> Path:
    """The shared WSI fields `numbers` as a curves file for `focustrack focus calibrate
    --curves` (JSONL, every measure of REAL_METRICS): what a user of another microscope
    would write from their own labelled curves."""
    fields = [f for f in load_wsi_fields(real_dir / "wsi_focus_curves") if f.number in numbers]
    write_curves(path, wsi_curves(fields, REAL_METRICS))
    return path


#: The measures `--calibrate-on` runs through the command (a 3-5 minute default run): the
#: three gradient measures of the targets, and one of each other kind (broad, offset,
#: unusable on this microscope).
HOLDOUT_METRICS = (
    "BRENNER",
    "_3_3_SOBEL",
    "SQUARED_GRADIENT",
    "NORMALIZED_VARIANCE",
    "JPEG",
    "VOLLATH_F4",
)
#: The halves of the shared WSI fields: name -> field numbers.
HALVES = {"odd": tuple(range(1, 21, 2)), "even": tuple(range(2, 21, 2))}
#: The targets on the held-out half after `calibrate` on the other: (name, part, key, test).
HOLDOUT_TARGETS = (
    ("2-sigma coverage on 11x3 windows >= 92%", "windows_11x3", "coverage_2sigma", 0.92, 1),
    ("edge flags right >= 98%", "windows", "edge_right", 0.98, 1),
    ("edge flags wrong <= 0.5%", "windows", "edge_wrong", 0.005, -1),
    ("confident-wrong <= 0.1%", "windows", "silent_miss", 0.001, -1),
)
#: ... and with no profile at all.
NO_PROFILE_TARGETS = (
    ("2-sigma coverage on 11x3 windows >= 85%", "windows_11x3", "coverage_2sigma", 0.85, 1),
    ("confident-wrong <= 0.2%", "windows", "silent_miss", 0.002, -1),
)


def holdout_misses(
    figures: dict[str, dict], targets: tuple, unusable: Collection[str] = ()
) -> dict[str, list[str]]:
    """Each target -> the usable metrics whose figures miss it (NaN misses)."""
    out: dict[str, list[str]] = {}
    for name, part, key, bound, sense in targets:
        out[name] = [
            metric
            for metric, parts in figures.items()
            if metric not in unusable and not sense * (parts[part][key] - bound) >= 0
        ]
    return out


def half_fields(real_dir: Path, half: str) -> list[LabelledCurve]:
    """The shared WSI fields of one half (`HALVES`) as labelled curves."""
    folder = real_dir / "wsi_focus_curves"
    return wsi_curves([f for f in load_wsi_fields(folder) if f.number in HALVES[half]])


def read_without_profile(
    fields: Sequence[LabelledCurve], metrics: Collection[str]
) -> dict[str, dict]:
    """Per metric, the figures (`calibration.parts`) of `fields` read as the curve endpoint
    reads a curve labelled with the metric's name and no profile: none of the WSI names is a
    service metric, so each is a metric the service knows nothing of (`unprofiled`)."""
    empty = MicroscopeProfile({})
    return {
        metric: parts(read_fields(fields, metric, empty.settings_for(metric, FocusSettings())))
        for metric in metrics
    }


def calibrate_and_hold_out(
    real_dir: Path, calibrate_on: str, metrics: Collection[str], workdir: Path, folds: int
) -> dict:
    """`focustrack focus calibrate` on one half of the WSI fields, run as a user runs it (its
    curves file written first, the command's own entry point), then the other half read
    through the focus service's curve path with the profile it wrote, and without one."""
    from focustrack.cli import main  # the command as a user calls it

    held_out = next(name for name in HALVES if name != calibrate_on)
    curves = write_wsi_curves(real_dir, HALVES[calibrate_on], workdir / f"{calibrate_on}.jsonl")
    profile_path = workdir / f"profile_{calibrate_on}.json"
    argv = ["focus", "calibrate", "--curves", str(curves), "--out", str(profile_path)]
    if main([*argv, "--folds", str(folds), "--metrics", *metrics]) != 0:
        raise SystemExit(f"focustrack focus calibrate failed on {curves}")
    profile = MicroscopeProfile.load(profile_path)
    fields = half_fields(real_dir, held_out)
    with_profile = {
        metric: parts(read_fields(fields, metric, profile.settings_for(metric, FocusSettings())))
        for metric in metrics
    }
    without = read_without_profile(fields, metrics)
    unusable = [m for m, entry in profile.metrics.items() if not entry.usable]
    return {
        "calibrate_on": calibrate_on,
        "held_out": held_out,
        "profile": str(profile_path),
        "unusable": unusable,
        "with_profile": with_profile,
        "no_profile": without,
        "targets": holdout_misses(with_profile, HOLDOUT_TARGETS, unusable),
        "no_profile_targets": holdout_misses(without, NO_PROFILE_TARGETS),
    }


def print_holdout(result: dict) -> None:
    """One direction's held-out figures and targets."""
    title = (
        f"held-out {result['held_out']} fields, profile learnt on the {result['calibrate_on']} "
        f"ones ({result['profile']})"
    )
    print_report(result["with_profile"], title, result["unusable"])
    print_report(result["no_profile"], f"held-out {result['held_out']} fields, no profile")
    for heading, misses in (
        ("with the profile (usable metrics)", result["targets"]),
        ("with no profile", result["no_profile_targets"]),
    ):
        print(f"  targets {heading}:")
        for target, missed in misses.items():
            print(f"    {'NOT met' if missed else 'met    '}  {target}  {' '.join(missed)}")


def write_holdout_plot(path: Path, results: list[dict]) -> None:
    """Held-out coverage (11x3), edge right and wrong, confident-wrong per metric, both ways,
    with and without the profile."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [(part, key) for _, part, key, _, _ in HOLDOUT_TARGETS]
    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 4), sharey=True)
    names = list(results[0]["with_profile"])
    bars = [
        (f"{r['calibrate_on']}->{r['held_out']}{suffix}", r[which])
        for r in results
        for which, suffix in (("with_profile", ""), ("no_profile", " (none)"))
    ]
    height = 0.8 / len(bars)
    for ax, (part, key) in zip(axes, keys, strict=True):
        for i, (label, figures) in enumerate(bars):
            values = [figures[m][part][key] for m in names]
            ax.barh(np.arange(len(names)) + i * height, values, height=height, label=label)
        ax.set(title=f"{key} ({part})")
    axes[0].set_yticks(np.arange(len(names)) + 0.4, names, fontsize=7)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """`--real`: the WSI curves' figures on the report fields (and the fit fields), targets."""
    folder = args.real_dir / "wsi_focus_curves"
    if not folder.is_dir():
        return refuse("bench focus", f"--real needs {folder}, which is missing (see its README)")
    if args.calibrate_on == "none":
        return run_without_profile(args)
    if args.calibrate_on:
        return run_calibrated(args)
    metrics = REAL_METRICS
    constants = calibration.calibrate(folder, tqdm(metrics, desc="real curves", unit="metric"))
    readings = calibration.real_curves(
        folder, tqdm(metrics, desc="real curves", unit="metric"), calibration=constants
    )
    report = calibration.report(readings, calibration.REPORT_FIELDS)
    fit = calibration.report(readings, calibration.FIT_FIELDS)
    print(
        f"source: {folder} (real WSI curves, {WSI_STEP_UM} um steps); errors, sigma "
        "in steps against the hand label; coverage allows half a step for its rounding"
    )
    unusable = {m: c.unusable_because for m, c in constants.items() if not c.usable}

    def systematic(c: calibration.Calibration) -> str:
        if c.systematic_sigma_steps is None:  # none up to the cap reached the coverage
            return f"{'>' + str(calibration.MEDIAN_SIGMA_TARGET_STEPS):>8}"
        return f"{c.systematic_sigma_steps:>8.2f}"

    print(
        "learnt on the fit fields per measure: noise (share of the maximum) and systematic "
        f"sigma (steps, for {calibration.CALIBRATION_COVERAGE:.0%} coverage):\n  "
        + "\n  ".join(
            f"{metric:<24}{c.relative_noise:>10.2g}{systematic(c)}"
            + ("" if c.usable else f"  UNUSABLE: {c.unusable_because}")
            for metric, c in constants.items()
        )
    )
    print_report(report, "report fields 2, 4, ..., 20 (not used to fit)", unusable)
    print_report(fit, "fit fields 1, 3, ..., 19 (the constants were chosen here)", unusable)
    met = targets(report, unusable)
    print("\ntargets on the report fields (measures usable on this microscope):")
    for target, misses in met.items():
        print(f"  {'NOT met' if misses else 'met    '}  {target}  {' '.join(misses)}")
    unusable_met = unusable_targets(report, unusable)
    for metric, verdict in unusable_met.items():
        print(
            f"\n{metric}: unusable on this microscope (learnt on the fit fields: "
            f"{unusable[metric]}); every result it gives is flat, a warning with no z.\n"
            f"  meets: {'; '.join(verdict['met']) or '-'}\n"
            f"  cannot meet: {'; '.join(verdict['not_met']) or '-'} (a flat result has no z "
            "or sigma to cover, and a measure that points nowhere never points the right way)"
        )
    if args.json:
        payload = {
            "source": "wsi_focus_curves",
            "step_um": WSI_STEP_UM,
            "report_fields": list(calibration.REPORT_FIELDS),
            "fit_fields": list(calibration.FIT_FIELDS),
            "calibration": {m: asdict(c) for m, c in constants.items()},
            "metrics": report,
            "fit_metrics": fit,
            "targets": met,
            "unusable": {
                m: {"because": unusable[m]} | verdict for m, verdict in unusable_met.items()
            },
        }
        write_json(args.json, payload)
        print(f"wrote {args.json}")
    if args.plots:
        write_plot(args.plots / "real_curves.png", report)
        print(f"wrote {args.plots / 'real_curves.png'}")
    return 0


def run_calibrated(args: argparse.Namespace) -> int:
    """`--real --calibrate-on`: the calibrate command on one half, the other half reported."""
    halves = ("odd", "even") if args.calibrate_on == "both" else (args.calibrate_on,)
    metrics = HOLDOUT_METRICS
    with tempfile.TemporaryDirectory() as scratch:
        workdir = args.json.parent if args.json else Path(scratch)
        results = []
        for half in halves:
            print(f"\n== focustrack focus calibrate on the {half} fields ==")
            results.append(
                calibrate_and_hold_out(args.real_dir, half, metrics, workdir, args.folds)
            )
        for result in results:
            print_holdout(result)
    if args.json:
        write_json(args.json, {"source": "wsi_focus_curves", "runs": results})
        png = args.json.with_suffix(".png")
        write_holdout_plot(png, results)
        print(f"wrote {args.json}, {png}")
    return 0


def run_without_profile(args: argparse.Namespace) -> int:
    """`--real --calibrate-on none`: each half of the WSI fields read with no profile alone
    (the "none" columns of `--calibrate-on both`, without the command's runs)."""
    results = []
    for half in HALVES:
        figures = read_without_profile(half_fields(args.real_dir, half), HOLDOUT_METRICS)
        misses = holdout_misses(figures, NO_PROFILE_TARGETS)
        print_report(figures, f"{half} fields, no profile")
        print("  targets with no profile:")
        for target, missed in misses.items():
            print(f"    {'NOT met' if missed else 'met    '}  {target}  {' '.join(missed)}")
        results.append({"held_out": half, "no_profile": figures, "no_profile_targets": misses})
    if args.json:
        write_json(args.json, {"source": "wsi_focus_curves", "runs": results})
        print(f"wrote {args.json}")
    return 0
