"""`focustrack focus calibrate`: a microscope profile learnt from a user's labelled focus curves.

In: ``--curves FILE.jsonl`` (one field a line, `focustrack_focus.labelled_curves`), or
``--stacks DIR`` (z-stacks as TIFF or .npy, frames first, and ``DIR/labels.json``:
``{"FILE": {"z_um": [...], "focus_z_um": z}, ...}``; every stack is scored with the
focus service's metrics). Per metric (`focustrack_focus.calibration.cross_validate`):
the noise floor, the systematic sigma, whether it is usable, the curve's width and the
lean search's coarse step, with a cross-validation over fields whose folds' figures
(2-sigma coverage, edge flags right and wrong, confident-wrong) are printed. Out:
``--out PROFILE.json`` (`serve focus --profile PROFILE.json`) and a PNG of the fits beside
it (the curves aligned on their labels; the held-out windows' error / sigma).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from focustrack.arguments import output_file, refuse
from focustrack_core.stacks import decode_stack
from focustrack_focus import calibration
from focustrack_focus.labelled_curves import CurvesFileError, LabelledCurve, load_curves
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import validate_curve
from focustrack_focus.pipeline import FocusSettings, focus_scores
from focustrack_focus.profile import MicroscopeProfile

#: The figures printed per fold: (key in `calibration.summarise`, part, heading, format).
FOLD_COLUMNS = (
    ("within_1_step", "windows", "<=1 step", "%"),
    ("coverage_2sigma", "full", "cov full", "%"),
    ("coverage_2sigma", "windows", "cov win", "%"),
    ("coverage_2sigma", "windows_11x3", "cov 11x3", "%"),
    ("median_sigma_steps", "windows_11x3", "sig 11x3", "f"),
    ("edge_right", "windows", "edge ok", "%"),
    ("edge_wrong", "windows", "edge bad", "%"),
    ("silent_miss", "windows", "conf-wrong", "%"),
)
#: Largest stack file read by --stacks, bytes, and its decoded size.
MAX_STACK_BYTES = 2 << 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--curves",
        type=Path,
        metavar="FILE.jsonl",
        help='labelled curves, one field a line: {"z_um": [...], "scores": {"METRIC": [...]}, '
        '"focus_z_um": z}',
    )
    source.add_argument(
        "--stacks",
        type=Path,
        metavar="DIR",
        help="z-stacks (TIFF or .npy, frames first) and DIR/labels.json: "
        '{"FILE": {"z_um": [...], "focus_z_um": z}}',
    )
    parser.add_argument("--out", type=output_file, required=True, metavar="PROFILE.json")
    parser.add_argument(
        "--metrics", nargs="*", help="calibrate these metrics only (default: every one given)"
    )
    parser.add_argument(
        "--folds", type=int, default=5, help="cross-validation folds over fields (default 5)"
    )
    parser.add_argument(
        "--plot", type=output_file, metavar="PNG", help="the fits' figure (default: beside --out)"
    )


def stack_curves(folder: Path, metrics: list[str]) -> list[LabelledCurve]:
    """Labelled curves of the stacks in `folder` (`labels.json` names them), scored with
    each of `metrics` (the focus service's, default preprocessing)."""
    labels_path = folder / "labels.json"
    try:
        labels = json.loads(labels_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:  # ValueError: not JSON, or not UTF-8 text
        raise CurvesFileError(f"{labels_path}: {error}") from None
    if not isinstance(labels, dict) or not labels:
        raise CurvesFileError(f'{labels_path}: want {{"FILE": {{"z_um": [...], "focus_z_um": z}}}}')
    curves = []
    for number, (name, label) in enumerate(sorted(labels.items()), start=1):
        try:
            frames = decode_stack((folder / name).read_bytes(), 100_000, MAX_STACK_BYTES)
            z_um = np.asarray(label["z_um"], dtype=np.float64)
            focus = float(label["focus_z_um"])
            scores = {
                metric: focus_scores(frames, FocusSettings(metric=metric)) for metric in metrics
            }
            for values in scores.values():
                validate_curve(z_um, values)
        except (OSError, KeyError, TypeError, ValueError) as error:
            raise CurvesFileError(f"{folder / name}: {error}") from None
        order = np.argsort(z_um)
        sorted_scores = {metric: values[order] for metric, values in scores.items()}
        curves.append(LabelledCurve(number, z_um[order], sorted_scores, focus))
    return curves


def _cell(value: float, kind: str) -> str:
    if math.isnan(value):  # nothing to count (an unusable metric measures nothing)
        return f"{'-':>11}"
    return f"{value:>11.1%}" if kind == "%" else f"{value:>11.2f}"


def print_folds(metric: str, constants: calibration.Calibration, folds: list, fwhm: str) -> None:
    systematic = (
        "none reaches the coverage"
        if constants.systematic_sigma_steps is None
        else f"{constants.systematic_sigma_steps * constants.step_um:.3f} um"
    )
    print(
        f"\n{metric}: noise {constants.relative_noise:.2g} of the maximum, systematic sigma "
        f"{systematic}, {fwhm}"
        + ("" if constants.usable else f"\n  UNUSABLE: {constants.unusable_because}")
    )
    print(f"  {'held out':<14}{'sys um':>8}" + "".join(f"{c[2]:>11}" for c in FOLD_COLUMNS))
    for fold in folds:
        sys_steps = fold.constants.systematic_sigma_steps
        sys_um = "none" if sys_steps is None else f"{sys_steps * constants.step_um:.3f}"
        cells = [_cell(fold.figures[part][key], kind) for key, part, _, kind in FOLD_COLUMNS]
        held = ",".join(map(str, fold.held_out))
        print(
            f"  {held:<14}{sys_um:>8}"
            + "".join(cells)
            + ("" if fold.constants.usable else "  unusable")
        )
    pooled = calibration.parts([r for fold in folds for r in fold.readings])
    cells = [_cell(pooled[part][key], kind) for key, part, _, kind in FOLD_COLUMNS]
    print(f"  {'all folds':<14}{'':>8}" + "".join(cells))


def write_plot(
    path: Path,
    fields: dict[str, list[LabelledCurve]],
    results: dict[str, tuple[calibration.Calibration, list]],
) -> None:
    """Per metric: its curves (in `fields`, the metric's) aligned on their labels (scaled
    to their range), and the held-out readings' error over the coverage's bound (2 sigma +
    half a step; inside +-1: covered)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(2, len(names), figsize=(4 * len(names), 7), squeeze=False)
    for column, metric in enumerate(names):
        top, bottom = axes[0, column], axes[1, column]
        for curve in fields[metric]:
            s = curve.scores[metric]
            top.plot(curve.z_um - curve.focus_z_um, (s - s.min()) / np.ptp(s), lw=0.6, alpha=0.5)
        top.axvline(0.0, color="k", ls="--", lw=0.8)
        top.set(title=metric, xlabel="z - label (um)", ylabel="score (scaled)")
        # the coverage's own test: |error| <= 2 sigma + half a step (the label's rounding)
        ratios = np.array(
            [
                r.error_steps / (2.0 * r.sigma_steps + 0.5)
                for fold in results[metric][1]
                for r in fold.readings
                if r.label_side == 0 and r.error_steps is not None and r.sigma_steps is not None
            ]
        )
        if ratios.size:  # an unusable metric measures nothing
            bottom.hist(np.clip(ratios, -3, 3), bins=60, range=(-3, 3))
            covered = float(np.mean(np.abs(ratios) <= 1.0))
            bottom.set_title(f"held out: {covered:.1%} covered", fontsize=9)
        else:
            bottom.set_title("unusable: nothing measured", fontsize=9)
        bottom.axvspan(-1.0, 1.0, color="green", alpha=0.1)
        bottom.set(xlabel="error / (2 sigma + half a step)", ylabel="readings", xlim=(-3, 3))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def calibrate_profile(
    fields: dict[str, list[LabelledCurve]], n_folds: int, source: str
) -> tuple[MicroscopeProfile, dict[str, tuple[calibration.Calibration, list]]]:
    """Every metric's entry, learnt on its fields (`fields`: metric -> the fields it is
    calibrated on; cross-validated, printed as it goes) and the folds behind it."""
    entries, results = {}, {}
    for metric, curves in fields.items():
        constants, folds = calibration.cross_validate(curves, metric, n_folds)
        widths = calibration.curve_widths_um(curves, metric)
        # the narrowest tenth of the peaks still has a frame above its half maximum
        coarse = float(np.percentile(widths, 10)) if widths else None
        fwhm = constants.curve_fwhm_um
        width_text = "width unknown" if fwhm is None else f"curve FWHM {fwhm:.2f} um"
        print_folds(metric, constants, folds, width_text)
        pooled = calibration.parts([r for fold in folds for r in fold.readings])
        record = {
            "folds": [{"held_out": list(f.held_out), "figures": f.figures} for f in folds],
            "pooled": pooled,
        }
        entries[metric] = constants.entry(
            coarse_step_um=None if coarse is None else round(coarse, 2),
            cross_validation=_finite(record),
        )
        results[metric] = (constants, folds)
    return MicroscopeProfile(entries, source), results


def _finite(value: Any) -> Any:
    """`value` with every NaN (a figure with nothing to count) as None: plain JSON."""
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_finite(item) for item in value]
    return None if isinstance(value, float) and math.isnan(value) else value


def _fields(numbers: list[int]) -> str:
    """Field numbers as a user reads them ("field 3", "fields 3, 7"): a field is numbered by
    its "field", else by its line (`labelled_curves`)."""
    return f"field{'s' if len(numbers) > 1 else ''} {', '.join(map(str, numbers))}"


def run(args: argparse.Namespace) -> int:
    try:
        if args.curves is not None:
            curves = load_curves(args.curves)
        else:
            curves = stack_curves(args.stacks, args.metrics or list(METRICS))
    except (CurvesFileError, OSError) as error:
        return refuse("focus calibrate", str(error))
    source = str(args.curves or args.stacks)
    # metric -> the fields without its scores: a metric asked for must be in every field,
    # and one not asked for that some field lacks is left out, with a line saying so
    named = args.metrics or sorted({metric for curve in curves for metric in curve.scores})
    lacking = {m: [c.number for c in curves if m not in c.scores] for m in named}
    for metric, numbers in lacking.items():
        if numbers and args.metrics:
            return refuse("focus calibrate", f"{source}: no {metric} scores in {_fields(numbers)}")
    metrics = [metric for metric in named if not lacking[metric]]
    if not metrics:
        return refuse("focus calibrate", f"{source}: no metric is scored in every field")
    if len(curves) < 2:
        return refuse(
            "focus calibrate",
            f"{source} has only 1 field: cross-validation over fields needs at least 2",
        )
    if not 2 <= args.folds <= len(curves):
        return refuse(
            "focus calibrate",
            f"--folds must be 2 .. {len(curves)} (the fields of {source}), got {args.folds}",
        )
    # metric -> the fields it is calibrated on, and those where it scores nothing above 0
    fields, blank = {}, {}
    for metric in metrics:
        fields[metric], blank[metric] = calibration.scored_fields(curves, metric)
        if len(fields[metric]) < args.folds:
            return refuse(
                "focus calibrate",
                f"{metric} scores above 0 in only {len(fields[metric])} of the {len(curves)} "
                f"fields ({_fields(blank[metric])}: every score 0 or below), fewer than "
                f"--folds {args.folds}: lower --folds, or leave {metric} out (--metrics)",
            )
    print(
        f"{len(curves)} labelled fields, {len(metrics)} metrics, {args.folds}-fold "
        "cross-validation over fields (each fold's constants learnt on the others); errors "
        "and sigma in z steps"
    )
    for metric, numbers in lacking.items():
        if numbers:
            print(f"{metric} left out: no {metric} scores in {_fields(numbers)}")
    for metric, numbers in blank.items():
        if numbers:
            print(f"{metric}: {_fields(numbers)} left out, every score 0 or below there")
    profile, results = calibrate_profile(fields, args.folds, source)
    profile.save(args.out)
    plot = args.plot or args.out.with_suffix(".png")
    write_plot(plot, fields, results)
    print(f"\nwrote {args.out} (serve focus --profile {args.out}) and {plot}")
    return 0
