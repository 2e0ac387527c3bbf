"""`focustrack bench focus`: accuracy and speed of the focus metrics and of the peak fit.

Accuracy: simulated z-stacks with a known best focus (this module's own small
brightfield renderer, `synthetic_stack`: a specimen of cells and granules
whose Gaussian defocus blur grows with |z - z_true|, Poisson photon noise and
read noise on a 12-bit camera; fields of cells, of cells under dust on the
cover glass ("debris"), and empty fields), over several light levels and z
steps; mean and 90th-percentile |error|, the spread of the z-scores
(error / sigma), and how often a specimen gave no measurement or an empty
field was not flagged flat. Then the real stacks in ../shared/data/real/.

Speed: frames per second of preprocessing + metric for 2048x2048 uint16 and
1024x1024 RGB frames on one core, beside a plain in-memory copy of the same
frames; `copy_ratio` is metric time / copy time for the 2048x2048 frames.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from focustrack.services.estimator.strategy import FocusFlag
from focustrack.services.focus.metrics import DEFAULT_METRIC, METRICS
from focustrack.services.focus.peak import PeakMode, PeakSettings
from focustrack.services.focus.pipeline import FocusSettings, focus_from_curve, focus_scores
from focustrack.services.focus.preprocess import Preprocess, lowpass_sigma_for_optics

#: Optics of the synthetic microscope (60x/0.85 as in the thesis, 0.1 um pixels).
PIXEL_UM = 0.1
NA = 0.85
#: Gaussian sigma of the geometric defocus blur per um of defocus: the blur disc has
#: radius dz tan(asin NA), and a uniform disc of radius r has sigma r / 2.
DEFOCUS_SIGMA_PER_UM = math.tan(math.asin(NA)) / 2.0
READ_NOISE_E = 2.0
FULL_WELL = 4095  # 12-bit camera, 1 e-/ADU
DEBRIS_OFFSET_UM = 3.0  # dust on the cover glass, above the specimen

FIELDS = ("cells", "debris", "empty")
PHOTONS = (2000.0, 200.0, 30.0)
#: z step (um) -> frames per stack
STEPS = {0.25: 17, 0.5: 13, 1.0: 11}

REAL_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"
YEAST_FOCUS_PLANE = 17  # the source project's label (README of the yeast folder)


def _disc_layer(
    rng: np.random.Generator,
    size_px: int,
    count: int,
    radius_px: tuple[float, float],
    absorption: tuple[float, float],
) -> np.ndarray:
    """(size, size) float32 absorption of `count` discs, edges softened by 1 px."""
    layer = np.zeros((size_px, size_px), np.float32)
    for _ in range(count):
        centre = (int(rng.integers(0, size_px)), int(rng.integers(0, size_px)))
        radius = round(rng.uniform(*radius_px))
        cv2.circle(layer, centre, radius, float(rng.uniform(*absorption)), thickness=-1)
    return cv2.GaussianBlur(layer, (0, 0), 1.0)


def _blur(image: np.ndarray, defocus_um: float) -> np.ndarray:
    """In-focus PSF (at 0.55 um) and the defocus blur of `defocus_um`, in quadrature."""
    psf_px = 0.21 * 0.55 / NA / PIXEL_UM
    sigma_px = math.hypot(psf_px, DEFOCUS_SIGMA_PER_UM * defocus_um / PIXEL_UM)
    return cv2.GaussianBlur(image, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def synthetic_stack(
    rng: np.random.Generator,
    z_um: np.ndarray,
    z_true_um: float,
    *,
    field: str = "cells",
    photons: float = 1000.0,
    size_px: int = 160,
) -> np.ndarray:
    """A simulated brightfield z-stack (n, size, size) uint16 taken at z_um (n,) um.

    field: "cells" (cells and small dark granules in the focal plane), "debris"
    (the same under dust DEBRIS_OFFSET_UM above) or "empty" (no specimen).
    photons: mean photo-electrons per pixel of the background.
    """
    if field not in FIELDS:
        raise ValueError(f"unknown field {field!r}; known: {', '.join(FIELDS)}")
    specimen = np.zeros((size_px, size_px), np.float32)
    dust = np.zeros_like(specimen)
    if field != "empty":
        area = (size_px / 160) ** 2
        specimen = _disc_layer(rng, size_px, int(6 * area) + 1, (18, 30), (0.1, 0.25))
        specimen += _disc_layer(rng, size_px, int(40 * area) + 1, (1.5, 4), (0.3, 0.6))
    if field == "debris":
        dust = _disc_layer(rng, size_px, 3, (3, 8), (0.6, 0.9))
    transmission = np.clip(1.0 - specimen, 0.05, 1.0)
    dust_transmission = np.clip(1.0 - dust, 0.05, 1.0)
    frames = np.empty((len(z_um), size_px, size_px), np.uint16)
    for i, z in enumerate(z_um):
        image = _blur(transmission, z - z_true_um)
        if field == "debris":
            image = image * _blur(dust_transmission, z - z_true_um - DEBRIS_OFFSET_UM)
        electrons = rng.poisson(photons * image) + rng.normal(0.0, READ_NOISE_E, image.shape)
        frames[i] = np.clip(np.rint(electrons), 0, FULL_WELL)
    return frames


@dataclass
class Trial:
    """One stack read by one metric: truth and what was found (um)."""

    field: str
    photons: float
    step_um: float
    error_um: float | None  # None when there was no measurement
    sigma_um: float | None
    flags: frozenset[FocusFlag]


def simulate(
    settings_by_metric: dict[str, FocusSettings], reps: int, seed: int, size_px: int
) -> dict[str, list[Trial]]:
    """Every metric on the same simulated stacks: reps per (field, light, step)."""
    rng = np.random.default_rng(seed)
    trials: dict[str, list[Trial]] = {name: [] for name in settings_by_metric}
    jobs = [(f, p, s) for f in FIELDS for p in PHOTONS for s in STEPS for _ in range(reps)]
    for field, photons, step_um in tqdm(jobs, desc="simulated stacks", unit="stack"):
        n_frames = STEPS[step_um]
        z_um = step_um * (np.arange(n_frames) - (n_frames - 1) / 2)
        z_true_um = float(rng.uniform(-0.25, 0.25) * (z_um[-1] - z_um[0]))
        frames = synthetic_stack(
            rng, z_um, z_true_um, field=field, photons=photons, size_px=size_px
        )
        for name, settings in settings_by_metric.items():
            result = focus_from_curve(z_um, focus_scores(frames, settings), settings)
            observed = result.sigma_um is not None
            trials[name].append(
                Trial(
                    field,
                    photons,
                    step_um,
                    result.best_z_um - z_true_um if observed else None,
                    result.sigma_um,
                    result.flags,
                )
            )
    return trials


def summarise(trials: list[Trial]) -> dict[str, float]:
    """mae_um, p90_um, zscore_std (and robust spread) over specimen fields; miss and flat rates."""
    specimen = [t for t in trials if t.field != "empty"]
    measured = [t for t in specimen if t.error_um is not None]
    errors = np.array([t.error_um for t in measured])
    zscores = errors / np.array([t.sigma_um for t in measured])
    empty = [t for t in trials if t.field == "empty"]
    cells = [t for t in measured if t.field == "cells"]
    return {
        "mae_um": float(np.mean(np.abs(errors))),
        "p90_um": float(np.percentile(np.abs(errors), 90)),
        "mae_cells_um": float(np.mean([abs(t.error_um) for t in cells])),
        "mae_debris_um": float(np.mean([abs(t.error_um) for t in measured if t.field == "debris"])),
        "zscore_std": float(np.std(zscores)),
        "zscore_mad_std": float(1.4826 * np.median(np.abs(zscores - np.median(zscores)))),
        "missed": 1.0 - len(measured) / len(specimen),
        "empty_flat": float(np.mean([FocusFlag.FLAT in t.flags for t in empty])),
    }


def breakdown(trials: list[Trial]) -> dict[tuple[float, float], float]:
    """MAE (um) on cell fields per (photons, step_um)."""
    return {
        (p, s): float(
            np.mean(
                [
                    abs(t.error_um)
                    for t in trials
                    if t.field == "cells"
                    and t.photons == p
                    and t.step_um == s
                    and t.error_um is not None
                ]
                or [np.nan]
            )
        )
        for p in PHOTONS
        for s in STEPS
    }


def speed(settings: FocusSettings, frames: np.ndarray, min_s: float) -> float:
    """Frames per second of preprocessing + metric over `frames` (n, ...), repeated >= min_s."""
    done, started = 0, time.perf_counter()
    while True:
        focus_scores(frames, settings)
        done += len(frames)
        elapsed = time.perf_counter() - started
        if elapsed >= min_s:
            return done / elapsed


def copy_speed(frames: np.ndarray, min_s: float) -> float:
    """Frames per second of copying `frames` (n, ...) one by one into a buffer."""
    buffer = np.empty_like(frames[0])
    done, started = 0, time.perf_counter()
    while True:
        for frame in frames:
            np.copyto(buffer, frame)
        done += len(frames)
        elapsed = time.perf_counter() - started
        if elapsed >= min_s:
            return done / elapsed


def speed_frames(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Four 2048x2048 uint16 and four 1024x1024x3 uint8 textured frames."""
    grey = synthetic_stack(rng, np.linspace(-0.5, 0.5, 4), 0.0, size_px=2048, photons=1000)
    small = grey[:, ::2, ::2]
    rgb = np.stack([small // 16, small // 20, small // 24], axis=-1).astype(np.uint8)
    return grey, rgb


def load_smear(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The lip smear stack: planes (n, h, w, 3) cropped to a common centre, and plane index (n,)."""
    planes = sorted(folder.glob("*.bmp"), key=lambda path: int(path.stem))
    images = [cv2.imread(str(path), cv2.IMREAD_COLOR_RGB) for path in planes]
    height = min(image.shape[0] for image in images)
    width = min(image.shape[1] for image in images)

    def centre(image: np.ndarray) -> np.ndarray:
        y0 = (image.shape[0] - height) // 2
        x0 = (image.shape[1] - width) // 2
        return image[y0 : y0 + height, x0 : x0 + width]

    return np.stack([centre(image) for image in images]), np.array(
        [int(p.stem) for p in planes], dtype=np.float64
    )


def load_yeast(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The yeast stack (34, 63, 60) uint16 and its z (um, 0.3 um steps, plane 0 at 0)."""
    import tifffile

    frames = tifffile.imread(folder / "zstack.tif")
    return frames, 0.3 * np.arange(frames.shape[0])


def real_data(settings_by_metric: dict[str, FocusSettings], real_dir: Path) -> dict[str, dict]:
    """Best plane per metric on the smear (label 0) and the yeast (label 17, both modes)."""
    out: dict[str, dict] = {}
    smear_dir, yeast_dir = real_dir / "lip_smear_zstack", real_dir / "yeast_brightfield_zstack"
    for name, settings in settings_by_metric.items():
        row: dict[str, object] = {}
        if smear_dir.is_dir():
            frames, index = load_smear(smear_dir)
            result = focus_from_curve(index, focus_scores(frames, settings), settings)
            row["smear_best_plane"] = result.best_z_um
            row["smear_flags"] = sorted(map(str, result.flags))
        if yeast_dir.is_dir():
            frames, z_um = load_yeast(yeast_dir)
            scores = focus_scores(frames, settings)
            for mode in PeakMode:
                valley = replace(settings, peak=replace(settings.peak, mode=mode))
                result = focus_from_curve(z_um, scores, valley)
                plane = None if result.best_z_um is None else result.best_z_um / 0.3
                row[f"yeast_{mode}_plane"] = plane
                row[f"yeast_{mode}_flags"] = sorted(map(str, result.flags))
        out[name] = row
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="fewer stacks, shorter timing")
    parser.add_argument(
        "--reps",
        type=int,
        default=None,
        help="stacks per (field, light, step) (default 8, quick 3)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=160, help="simulated frame size, px")
    parser.add_argument("--metrics", nargs="*", default=list(METRICS), choices=list(METRICS))
    parser.add_argument("--real-dir", type=Path, default=REAL_DIR)
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the figures as JSON")
    parser.add_argument("--plots", type=Path, metavar="DIR", help="write PNG plots here")


def run(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)  # one core: the figure the issue asks for
    reps = args.reps or (3 if args.quick else 8)
    sim_settings = {
        name: FocusSettings(
            preprocess=Preprocess(lowpass_sigma_px=lowpass_sigma_for_optics(PIXEL_UM, NA)),
            metric=name,
            peak=PeakSettings(),
        )
        for name in args.metrics
    }
    print(
        f"source: this module's synthetic brightfield stacks ({args.size}x{args.size} px, "
        f"{PIXEL_UM} um px, NA {NA}); {reps} stacks per field x light x step"
    )
    trials = simulate(sim_settings, reps, args.seed, args.size)
    summary = {name: summarise(t) for name, t in trials.items()}

    # The real stacks are small and not oversampled like a slide scanner's (the smear's
    # pixel size is not given; the yeast's 0.11 um px is about Nyquist): 1 px low-pass.
    real_settings = {
        name: FocusSettings(preprocess=Preprocess(lowpass_sigma_px=1.0), metric=name)
        for name in args.metrics
    }
    real = real_data(real_settings, args.real_dir) if args.real_dir.is_dir() else {}

    rng = np.random.default_rng(args.seed)
    grey, rgb = speed_frames(rng)
    min_s = 0.3 if args.quick else 1.0
    copy_grey, copy_rgb = copy_speed(grey, min_s), copy_speed(rgb, min_s)
    for name in tqdm(args.metrics, desc="speed", unit="metric"):
        settings = FocusSettings(metric=name)
        fps_grey, fps_rgb = speed(settings, grey, min_s), speed(settings, rgb, min_s)
        summary[name] |= {
            "fps_2048_u16": fps_grey,
            "fps_1024_rgb": fps_rgb,
            "copy_ratio": copy_grey / fps_grey,
        }

    print_report(summary, {n: breakdown(t) for n, t in trials.items()}, real, copy_grey, copy_rgb)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "source": "synthetic",
            "copy_fps_2048_u16": copy_grey,
            "copy_fps_1024_rgb": copy_rgb,
            "metrics": {n: summary[n] | {"real": real.get(n, {})} for n in args.metrics},
        }
        args.json.write_text(json.dumps(payload, indent=2))
        print(f"wrote {args.json}")
    if args.plots:
        write_plots(args.plots, trials, real_settings, args.real_dir)
    fps_default = summary.get(DEFAULT_METRIC, {}).get("fps_2048_u16", math.inf)
    if fps_default < 100:
        print(f"WARNING: the default metric runs at {fps_default:.0f} frames/s (< 100) here")
    return 0


def print_report(
    summary: dict[str, dict],
    by_cell: dict[str, dict],
    real: dict[str, dict],
    copy_grey: float,
    copy_rgb: float,
) -> None:
    print("\naccuracy on simulated stacks (cells + debris fields; |error| in um)")
    print(
        f"{'metric':<22}{'mae':>7}{'p90':>7}{'cells':>7}{'debris':>7}{'z std':>7}"
        f"{'z mad':>7}{'missed':>8}{'empty flat':>11}"
    )
    for name, row in summary.items():
        print(
            f"{name:<22}{row['mae_um']:7.3f}{row['p90_um']:7.3f}{row['mae_cells_um']:7.3f}"
            f"{row['mae_debris_um']:7.3f}{row['zscore_std']:7.2f}{row['zscore_mad_std']:7.2f}"
            f"{row['missed']:8.1%}{row['empty_flat']:11.1%}"
        )
    cells = list(next(iter(by_cell.values())))
    print("\nMAE (um) on cell fields by photons/px and z step")
    print(f"{'metric':<22}" + "".join(f"{f'{p:g}/{s:g}':>10}" for p, s in cells))
    for name, row in by_cell.items():
        print(f"{name:<22}" + "".join(f"{row[key]:10.3f}" for key in cells))
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
        f"\nspeed on one core (frames/s); copy: {copy_grey:.0f} (2048 u16), "
        f"{copy_rgb:.0f} (1024 RGB)"
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
        measured = [t for t in ts if t.field != "empty" and t.error_um is not None]
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
    axes[0].set(xlabel="|error| (um)", ylabel="stacks", title="best-focus error, simulated")
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
