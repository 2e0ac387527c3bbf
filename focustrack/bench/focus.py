"""`focustrack bench focus`: accuracy and speed of the focus metrics and of the peak fit.

Accuracy: z-stacks rendered by the project's instrument simulator
(`services/instrument_sim`: a Giemsa-stained blood smear in RGB, imaged through
the defocus OTF of a 60x / 0.85 objective, Poisson and read noise, 12-bit camera;
docs/instrument.md) against its known true focus. Fields: a full smear, a sparse
one (10-30 % of the cells), an empty one (plasma only) and a full one under dust
on a plane `MicroscopeSpec.dust_dz_um` (8 um) above ("debris"); over light levels
(exposures), z steps, stack lengths and frame sizes (128 px, about 14 um across,
is the scheduler's small tile). Per metric: mean and 90th-percentile |error|, the
spread of the z-scores (error / sigma), how often a z-score exceeds 3 (a wrong
focus reported as trustworthy), how often a specimen gave no measurement and how
often an empty field was not flagged flat. Then the real stacks in
../shared/data/real/.

Speed: frames per second of preprocessing + metric on one core for 2048x2048
uint16 frames (the simulator's green channel) and 1024x1024 RGB frames (the
simulator's uint16 RGB), beside a plain in-memory copy of the same frames;
`copy_ratio` is metric time / copy time for the 2048x2048 frames. Each figure is
the median over repeated passes of the thread's CPU time, so other jobs on the
machine slow it less than they would a wall-clock figure.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from focustrack.arguments import (
    count_number,
    existing_folder,
    output_file,
    output_folder,
    refuse,
    seed_number,
    whole_number,
)
from focustrack.bench import focus_real
from focustrack.bench.json_report import write_json
from focustrack_core.domain import FocusFlag
from focustrack_core.geometry import ScanGrid
from focustrack_focus.metrics import DEFAULT_METRIC, METRICS
from focustrack_focus.peak import MAD_TO_SIGMA, PeakMode
from focustrack_focus.pipeline import FocusSettings, focus_scores, focus_stack
from focustrack_focus.preprocess import Preprocess, lowpass_sigma_for_optics
from focustrack_focus.real_data import YEAST_FOCUS_PLANE, load_smear, load_yeast
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, Slide
from focustrack_instrument_sim.specimen import SpecimenSpec

#: Field kind -> the simulator's specimen with every field of that kind.
FIELD_SPECS = {
    "full": SpecimenSpec(empty_fraction=0.0, sparse_fraction=0.0),
    "sparse": SpecimenSpec(empty_fraction=0.0, sparse_fraction=1.0),
    "empty": SpecimenSpec(empty_fraction=1.0),
    "debris": SpecimenSpec(empty_fraction=0.0, sparse_fraction=0.0, dust_density=3.0),
}
FIELDS = tuple(FIELD_SPECS)
SPECIMEN_FIELDS = ("full", "sparse", "debris")
#: Exposures (s): 12 000, 1 200 and 120 photo-electrons per pixel through glass.
EXPOSURES_S = (10e-3, 1e-3, 0.1e-3)
#: (z step um, frames): the wide stacks of a first autofocus, and the scheduler's
#: narrow 5-frame stack around a confident prediction (ZRangePolicy defaults).
STACKS = ((0.25, 17), (0.5, 13), (1.0, 11), (0.5, 5))
SIZES_PX = (256, 128)
#: The bench's slide, and its grid pitch (only the tile seeds matter, not the travel).
BENCH_SLIDE = "bench"
_PITCH_UM = 10.0

REAL_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"


@dataclass(frozen=True)
class StackShape:
    """How one stack is taken: z step (um), frame count and exposure (s)."""

    step_um: float
    n_frames: int
    exposure_s: float


@dataclass(frozen=True)
class SimulatedStack:
    """A simulated z-stack: frames (n, size, size, 3) uint16 RGB at z_um (n,), true focus (um)."""

    z_um: np.ndarray
    frames: np.ndarray
    truth_um: float
    shape: StackShape


def _field_spec(field: str) -> SpecimenSpec:
    if field not in FIELD_SPECS:
        raise ValueError(f"unknown field {field!r}; known: {', '.join(FIELDS)}")
    return FIELD_SPECS[field]


def field_microscope(field: str, size_px: int, truth_um: np.ndarray, seed: int) -> Microscope:
    """A simulated microscope holding one slide, BENCH_SLIDE, of len(truth_um) tiles in a row.

    Every tile is a `field` kind of field, size_px x size_px; tile (0, i) has its
    true focus at truth_um[i] (um). `seed` draws the specimen and the camera noise.
    """
    truth = np.asarray(truth_um, dtype=np.float64).reshape(1, -1)
    spec = MicroscopeSpec(height=size_px, width=size_px, specimen=_field_spec(field))
    slide = Slide(BENCH_SLIDE, truth, ScanGrid(1, truth.size, _PITCH_UM), (seed, size_px))
    return Microscope([slide], spec, seed=seed)


def render_stack(
    field: str, size_px: int, z_um: np.ndarray, truth_um: float, seed: int
) -> np.ndarray:
    """Frames (n, size_px, size_px, 3) uint16 RGB of one tile whose true focus is truth_um,
    at the evenly spaced z_um (n,), default exposure."""
    scope = field_microscope(field, size_px, np.array([truth_um]), seed)
    step_um = float(z_um[1] - z_um[0])
    return scope.acquire(BENCH_SLIDE, 0, 0, float(z_um[0]), step_um, len(z_um)).pixels


def simulated_stacks(
    field: str, size_px: int, shapes: Sequence[StackShape], seed: int
) -> Iterator[SimulatedStack]:
    """One stack per entry of `shapes`, each of a new tile of `field`, from the simulator.

    The true focus of every tile is uniform in [-2, 2] um; each stack is centred
    within a quarter of its range of it (so the peak is inside, away from the edges).
    """
    _field_spec(field)  # an unknown field fails before any drawing
    rng = np.random.default_rng([seed, FIELDS.index(field), size_px])
    truth_um = rng.uniform(-2.0, 2.0, max(len(shapes), 1))
    scope = field_microscope(field, size_px, truth_um, seed)
    for col, shape in enumerate(shapes):
        range_um = shape.step_um * (shape.n_frames - 1)
        z_low_um = truth_um[col] + rng.uniform(-0.25, 0.25) * range_um - range_um / 2
        stack = scope.acquire(
            BENCH_SLIDE, 0, col, z_low_um, shape.step_um, shape.n_frames, shape.exposure_s
        )
        yield SimulatedStack(stack.z_um, stack.pixels, float(truth_um[col]), shape)


def bench_settings(metric: str, pixel_size_um: float | None = None) -> FocusSettings:
    """The settings the focus service uses on a simulator stack (green, low-pass matched)."""
    optics = MicroscopeSpec().optics
    pixel_um = optics.pixel_size_um if pixel_size_um is None else pixel_size_um
    sigma_px = lowpass_sigma_for_optics(pixel_um, optics.numerical_aperture)
    return FocusSettings(preprocess=Preprocess(lowpass_sigma_px=sigma_px), metric=metric)


@dataclass
class Trial:
    """One stack read by one metric: how it was taken and what was found (um)."""

    field: str
    size_px: int
    shape: StackShape
    error_um: float | None  # None when there was no measurement
    sigma_um: float | None
    flags: frozenset[FocusFlag]


def simulate(metrics: Sequence[str], reps: int, seed: int) -> dict[str, list[Trial]]:
    """Every metric on the same simulated stacks: `reps` per field, size, exposure and stack."""
    shapes = [
        StackShape(step, n, exposure)
        for exposure in EXPOSURES_S
        for step, n in STACKS
        for _ in range(reps)
    ]
    settings = {name: bench_settings(name) for name in metrics}
    trials: dict[str, list[Trial]] = {name: [] for name in metrics}
    total = len(FIELDS) * len(SIZES_PX) * len(shapes)
    with tqdm(total=total, desc="simulated stacks", unit="stack") as progress:
        for field in FIELDS:
            for size_px in SIZES_PX:
                for stack in simulated_stacks(field, size_px, shapes, seed):
                    for name, chosen in settings.items():
                        result = focus_stack(stack.frames, stack.z_um, chosen)
                        error = None
                        if result.sigma_um is not None and result.best_z_um is not None:
                            error = result.best_z_um - stack.truth_um
                        trials[name].append(
                            Trial(field, size_px, stack.shape, error, result.sigma_um, result.flags)
                        )
                    progress.update()
    return trials


def summarise(trials: list[Trial]) -> dict[str, float]:
    """Accuracy over specimen fields (um), z-score spread, miss and flat rates (fractions)."""
    specimen = [t for t in trials if t.field in SPECIMEN_FIELDS]
    measured = [t for t in specimen if t.error_um is not None]
    errors = np.array([t.error_um for t in measured])
    zscores = errors / np.array([t.sigma_um for t in measured])
    empty = [t for t in trials if t.field == "empty"]

    def field_mae(field: str) -> float:
        field_errors = [
            abs(t.error_um) for t in measured if t.field == field and t.error_um is not None
        ]
        return float(np.mean(field_errors or [np.nan]))

    def missed(field: str) -> float:
        of_field = [t for t in specimen if t.field == field]
        return sum(t.error_um is None for t in of_field) / len(of_field)

    return {
        "mae_um": float(np.mean(np.abs(errors))),
        "p90_um": float(np.percentile(np.abs(errors), 90)),
        "zscore_std": float(np.std(zscores)),
        "zscore_mad_std": float(MAD_TO_SIGMA * np.median(np.abs(zscores - np.median(zscores)))),
        "zscore_over_3": float(np.mean(np.abs(zscores) > 3.0)),
        **{f"mae_{field}_um": field_mae(field) for field in SPECIMEN_FIELDS},
        **{f"missed_{field}": missed(field) for field in SPECIMEN_FIELDS},
        "empty_flat": float(np.mean([FocusFlag.FLAT in t.flags for t in empty])),
    }


def breakdown(trials: list[Trial]) -> dict[str, dict[str, float]]:
    """Per (field, size) of the trials: MAE (um), z-score std and > 3 share, missed share."""
    out: dict[str, dict[str, float]] = {}
    for field in SPECIMEN_FIELDS:
        for size_px in SIZES_PX:
            group = [t for t in trials if t.field == field and t.size_px == size_px]
            measured = [t for t in group if t.error_um is not None]
            errors = np.array([t.error_um for t in measured])
            zscores = errors / np.array([t.sigma_um for t in measured]) if measured else errors
            out[f"{field} {size_px}px"] = {
                "mae_um": float(np.mean(np.abs(errors))) if measured else math.nan,
                "zscore_std": float(np.std(zscores)) if measured else math.nan,
                "zscore_over_3": float(np.mean(np.abs(zscores) > 3.0)) if measured else math.nan,
                "missed": 1.0 - len(measured) / len(group),
            }
    return out


def _median_cpu_s(work: Callable[[], object], repeats: int) -> float:
    """Median thread CPU time (s) of `work()` over `repeats` runs, after one warm-up run."""
    work()
    times = []
    for _ in range(repeats):
        started = time.thread_time()
        work()
        times.append(time.thread_time() - started)
    return float(np.median(times))


def speed(settings: FocusSettings, frames: np.ndarray, repeats: int) -> float:
    """Frames per second (one core) of preprocessing + metric over `frames` (n, ...)."""
    return len(frames) / _median_cpu_s(lambda: focus_scores(frames, settings), repeats)


def copy_speed(frames: np.ndarray, repeats: int) -> float:
    """Frames per second of copying `frames` (n, ...) one by one into a buffer."""
    buffer = np.empty_like(frames[0])

    def copy_all() -> None:
        for frame in frames:
            np.copyto(buffer, frame)

    return len(frames) / _median_cpu_s(copy_all, repeats)


def speed_frames(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Simulator frames near focus: 2048x2048 uint16 (green), (4, ...); and their centre as
    1024x1024 RGB uint16, (4, 1024, 1024, 3)."""
    shape = StackShape(0.25, 4, EXPOSURES_S[0])
    stack = next(simulated_stacks("full", 2048, [shape], seed))
    grey = np.ascontiguousarray(stack.frames[..., 1])
    rgb = np.ascontiguousarray(stack.frames[:, 512:1536, 512:1536, :])
    return grey, rgb


def real_data(settings_by_metric: dict[str, FocusSettings], real_dir: Path) -> dict[str, dict]:
    """Best plane per metric on the smear (label 0) and the yeast (label 17, both modes)."""
    out: dict[str, dict] = {}
    smear_dir, yeast_dir = real_dir / "lip_smear_zstack", real_dir / "yeast_brightfield_zstack"
    for name, settings in settings_by_metric.items():
        row: dict[str, object] = {}
        if smear_dir.is_dir():
            frames, index = load_smear(smear_dir)
            result = focus_stack(frames, index, settings)
            row["smear_best_plane"] = result.best_z_um
            row["smear_flags"] = sorted(map(str, result.flags))
        if yeast_dir.is_dir():
            frames, z_um = load_yeast(yeast_dir)
            for mode in PeakMode:
                valley = replace(settings, peak=replace(settings.peak, mode=mode))
                result = focus_stack(frames, z_um, valley)
                plane = None if result.best_z_um is None else result.best_z_um / 0.3
                row[f"yeast_{mode}_plane"] = plane
                row[f"yeast_{mode}_flags"] = sorted(map(str, result.flags))
        out[name] = row
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer stacks, fewer repeats")
    parser.add_argument(
        "--reps",
        type=count_number,
        default=None,
        help="stacks per field, size, exposure and stack shape (default 4, quick 1)",
    )
    parser.add_argument(
        "--seed",
        type=seed_number,
        default=1,
        help="simulation seed (default 1; the sigma model was fitted on seeds 100-102)",
    )
    parser.add_argument("--metrics", nargs="+", default=list(METRICS), choices=list(METRICS))
    # typed only when given: the default folder may be absent (the simulator's figures
    # leave its rows out), a folder given by hand that is not there is a mistake
    parser.add_argument("--real-dir", type=existing_folder, default=REAL_DIR)
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the figures as JSON")
    parser.add_argument("--plots", type=output_folder, metavar="DIR", help="write PNG plots here")
    parser.add_argument(
        "--real",
        action="store_true",
        help="instead of the simulator: real WSI focus curves (full and windows) from "
        "--real-dir/wsi_focus_curves, read as POST /v1/focus/curve reads them",
    )
    parser.add_argument(
        "--calibrate-on",
        choices=("odd", "even", "both", "none"),
        help="with --real: run `focustrack focus calibrate` on that half of the fields and "
        "report the other half with its profile and without one (both: each way; none: no "
        "command, each half with no profile alone, about a minute)",
    )
    parser.add_argument(
        "--folds",
        type=whole_number(2),  # a cross-validation needs a fold to hold out and one to fit
        default=5,
        help="with --calibrate-on: the command's --folds, >= 2 (default 5)",
    )


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)  # the target: a 100 frames/s camera kept up with on one core
    if args.calibrate_on and not args.real:
        return refuse("bench focus", "--calibrate-on needs --real")
    if args.real:
        return focus_real.run(args)
    reps = args.reps or (1 if args.quick else 4)
    print(
        f"source: the instrument simulator (docs/instrument.md), fields {'/'.join(FIELDS)}, "
        f"{'/'.join(map(str, SIZES_PX))} px, exposures "
        f"{'/'.join(f'{e * 1e3:g}' for e in EXPOSURES_S)} ms, stacks "
        f"{', '.join(f'{n}x{s:g} um' for s, n in STACKS)}; {reps} per combination, seed {args.seed}"
    )
    trials = simulate(args.metrics, reps, args.seed)
    summary = {name: summarise(t) for name, t in trials.items()}

    # The real stacks are small and not oversampled like a slide scanner's (the smear's
    # pixel size is not given; the yeast's 0.11 um px is about Nyquist): 1 px low-pass.
    real_settings = {
        name: FocusSettings(preprocess=Preprocess(lowpass_sigma_px=1.0), metric=name)
        for name in args.metrics
    }
    real = real_data(real_settings, args.real_dir) if args.real_dir.is_dir() else {}

    grey, rgb = speed_frames(args.seed)
    repeats = 5 if args.quick else 15
    load = os.getloadavg()[0]
    copy_grey, copy_rgb = copy_speed(grey, repeats), copy_speed(rgb, repeats)
    for name in tqdm(args.metrics, desc="speed", unit="metric"):
        settings = bench_settings(name)
        fps_grey, fps_rgb = speed(settings, grey, repeats), speed(settings, rgb, repeats)
        summary[name] |= {
            "fps_2048_u16": fps_grey,
            "fps_1024_rgb": fps_rgb,
            "copy_ratio": copy_grey / fps_grey,
        }

    by_group = {name: breakdown(t) for name, t in trials.items()}
    print_report(summary, by_group, real, copy_grey, copy_rgb, load)
    if args.json:
        payload = {
            "source": "instrument_sim",
            "seed": args.seed,
            "reps": reps,
            "load_average": load,
            "copy_fps_2048_u16": copy_grey,
            "copy_fps_1024_rgb": copy_rgb,
            "metrics": {
                n: summary[n] | {"by_field": by_group[n], "real": real.get(n, {})}
                for n in args.metrics
            },
        }
        write_json(args.json, payload)
        print(f"wrote {args.json}")
    if args.plots:
        write_plots(args.plots, trials, real_settings, args.real_dir)
    fps_default = summary.get(DEFAULT_METRIC, {}).get("fps_2048_u16", math.inf)
    if fps_default < 100:
        print(f"WARNING: the default metric runs at {fps_default:.0f} frames/s (< 100) here")
    return 0


def print_report(
    summary: dict[str, dict],
    by_group: dict[str, dict[str, dict[str, float]]],
    real: dict[str, dict],
    copy_grey: float,
    copy_rgb: float,
    load: float,
) -> None:
    print("\naccuracy on simulated stacks (full + sparse + debris fields; |error| in um)")
    print(
        f"{'metric':<22}{'mae':>7}{'p90':>7}{'full':>7}{'sparse':>7}{'debris':>7}{'z std':>7}"
        f"{'z mad':>7}{'|z|>3':>7}{'missed':>8}{'empty flat':>11}"
    )
    for name, row in summary.items():
        missed = np.mean([row[f"missed_{field}"] for field in SPECIMEN_FIELDS])
        print(
            f"{name:<22}{row['mae_um']:7.3f}{row['p90_um']:7.3f}{row['mae_full_um']:7.3f}"
            f"{row['mae_sparse_um']:7.3f}{row['mae_debris_um']:7.3f}{row['zscore_std']:7.2f}"
            f"{row['zscore_mad_std']:7.2f}{row['zscore_over_3']:7.1%}{missed:8.1%}"
            f"{row['empty_flat']:11.1%}"
        )
    groups = list(next(iter(by_group.values())))
    print("\nper field and frame size: MAE um / z-score std / share |z|>3 / missed")
    print(f"{'metric':<22}" + "".join(f"{group:>26}" for group in groups[:3]))
    for start in range(0, len(groups), 3):
        if start:
            print(f"{'':<22}" + "".join(f"{group:>26}" for group in groups[start : start + 3]))
        for name, rows in by_group.items():
            cells = [rows[group] for group in groups[start : start + 3]]
            print(
                f"{name:<22}"
                + "".join(
                    f"{c['mae_um']:>9.3f}{c['zscore_std']:>6.2f}{c['zscore_over_3']:>6.1%}"
                    f"{c['missed']:>5.0%}"
                    for c in cells
                )
            )
    if real:
        print("\nreal data: smear best plane (label 0); yeast best plane (label 17), max/valley")
        for name, row in real.items():
            smear = row.get("smear_best_plane")
            ymax, yval = row.get("yeast_max_plane"), row.get("yeast_valley_plane")
            print(
                f"{name:<22} smear {_fmt(smear)} {row.get('smear_flags', [])}"
                f"  yeast max {_fmt(ymax)} valley {_fmt(yval)} {row.get('yeast_valley_flags')}"
            )
    print(
        f"\nspeed on one core (frames/s, median thread CPU time; load average {load:.1f}); "
        f"copy: {copy_grey:.0f} (2048 u16), {copy_rgb:.0f} (1024 RGB)"
    )
    print(f"{'metric':<22}{'2048 u16':>10}{'1024 RGB':>10}{'copy ratio':>12}")
    for name, row in summary.items():
        print(
            f"{name:<22}{row['fps_2048_u16']:10.0f}{row['fps_1024_rgb']:10.0f}"
            f"{row['copy_ratio']:12.1f}"
        )


def _fmt(value: float | None) -> str:
    return "  none" if value is None else f"{value:6.2f}"


def write_plots(
    out_dir: Path,
    trials: dict[str, list[Trial]],
    real_settings: dict[str, FocusSettings],
    real_dir: Path,
) -> None:
    """errors.png (error histograms and z-scores per metric); real.png (the real curves)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, ts in trials.items():
        measured = [t for t in ts if t.field in SPECIMEN_FIELDS and t.error_um is not None]
        errors = np.array([t.error_um for t in measured])
        axes[0].hist(np.abs(errors), bins=40, histtype="step", label=name, range=(0, 1))
        axes[1].hist(
            errors / np.array([t.sigma_um for t in measured]),
            bins=40,
            histtype="step",
            label=name,
            range=(-5, 5),
            density=True,
        )
    grid = np.linspace(-5, 5, 200)
    axes[1].plot(grid, np.exp(-(grid**2) / 2) / math.sqrt(2 * math.pi), "k--", label="N(0, 1)")
    axes[0].set(xlabel="|error| (um)", ylabel="stacks", title="best-focus error, simulator")
    axes[1].set(xlabel="error / sigma", ylabel="density", title="z-scores")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "errors.png", dpi=120)
    plt.close(fig)

    if not real_dir.is_dir():
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    smear, index = load_smear(real_dir / "lip_smear_zstack")
    yeast, z_um = load_yeast(real_dir / "yeast_brightfield_zstack")
    for name, settings in real_settings.items():
        for ax, (frames, z) in zip(axes, [(smear, index), (yeast, z_um / 0.3)], strict=True):
            scores = focus_scores(frames, settings)
            ax.plot(z, (scores - scores.min()) / np.ptp(scores), label=name)
    axes[0].axvline(0, color="k", ls="--")
    axes[1].axvline(YEAST_FOCUS_PLANE, color="k", ls="--")
    axes[0].set(xlabel="plane", ylabel="score (scaled)", title="lip smear (label: plane 0)")
    axes[1].set(xlabel="plane", title="yeast, unstained (label: plane 17)")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "real.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out_dir / 'errors.png'}, {out_dir / 'real.png'}")
