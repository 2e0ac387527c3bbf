"""`focustrack bench slide`: realistic virtual slides scanned by every strategy through the
real services.

Each seed is one continuous tissue section (`--tissue-slide` of the simulator: empty glass,
holes, folds, tilt, a wedged coverslip with dust 10-170 um above the section, bubbles),
cut into tiles that overlap. The instrument, focus and estimator services run as
processes on loopback (`focustrack.local_stack.LocalStack`); every strategy scans every slide,
and the instrument's truth (evaluation only) says per tile the section's height, whether
the tile is empty glass and where its dust lies. Per strategy:

- tissue_in_focus_fraction: tissue tiles (not empty) whose kept frame (or one of its kept
  planes) lies within half the depth of field of the section (or of a fold's upper layer);
- tissue_stated_in_focus_fraction: the same as the estimator expected it, one minus the
  mean out-of-focus risk it stated for the tissue tiles' images (NaN where a strategy
  states none): a stated risk that holds is one where the two agree;
- frames_per_tile: frames acquired over tiles;
- time_over_limit: the simulated scan time over the physical limit (the serpentine's
  stage moves and one frame per tile);
- tissue_mae_um: the mean distance of the tissue tiles' kept frames from their section
  (or a fold's upper layer), um;
- tiles_focused_on_dust: tiles whose kept frame lies nearer their dust than their tissue;
- empty_tiles_frames: frames acquired per empty tile;
- phase_frames_per_tile, tiles_with_phase: with `--phase`, the frames of the phase stacks
  (`focustrack scan --phase`: a stack on every tile not found empty) over tiles, and the
  tiles whose phase came back;
- seam_error_px: the stitched mosaic's seams (the scan report's, `stitch.Placement`): the
  RMS of how far neighbours' overlaps still disagree once placed by the stage and refined.

Strategies that take `look_first` (kf-2d-lean and the other filters with the lean rule's
parameters; not kf-2d) scan with it on: a tile's first stack
is its lowest frame alone, then the rest where the focus service sees something in view
(`focustrack_estimator.look_first`); `--no-look-first` takes whole stacks, as before.

`--specimen` scans a slide of separate fields carrying one of the simulator's specimens
instead (a stained smear; unstained cells in culture or red cells, imaged with partially
coherent light), with the focus service in `--focus-mode` (by default the specimen's own:
valley for the unstained ones). Its tissue is every tile with specimen in view; its empty
tiles are those with none (the simulator's specimen says which, `slide_scores.bare_glass`);
there is no dust, fold or overlap to score.

    focustrack bench slide [--seeds 1 2] [--rows 10 --cols 10 --size 256]
                           [--specimen tissue|stained-smear|phase-cells|phase-blood]
                           [--focus-mode max|valley] [--phase] [--no-look-first]
                           [--json OUT]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from focustrack.arguments import (
    finite_number,
    output_file,
    output_folder,
    seed_number,
    whole_number,
)
from focustrack.bench.json_report import write_json
from focustrack.demo import scan_on, slide_problem
from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack
from focustrack.slide_scores import bare_glass, scored_scan
from focustrack_core.geometry import MAX_GRID_SIDE
from focustrack_core.surfaces import FAMILIES
from focustrack_estimator import registry
from focustrack_focus.peak import PeakMode
from focustrack_instrument_sim.simulator_options import (
    MAX_FRAME_SIDE_PX,
    SPECIMENS,
    SimulatorOptions,
)
from focustrack_scheduler.settings import BEST_KALMAN, ScanOptions

DEFAULT_STRATEGIES = (BEST_KALMAN, "kf-2d-lean", "survey-delaunay", "af-every-tile")
#: Kalman strategies: the best of them is held to the targets.
KALMAN_PREFIX = "kf-"
#: The smallest frame side the bench takes, px: tissue and dust to score need some pixels.
MIN_SIZE_PX = 64
#: `--specimen`'s default: the virtual tissue slide (`--tissue-slide` of the simulator).
TISSUE = "tissue"


@dataclass(frozen=True)
class SlideScore:
    """One strategy on one or more slides (see the module docstring)."""

    tissue_in_focus_fraction: float
    tissue_stated_in_focus_fraction: float
    tissue_mae_um: float
    frames_per_tile: float
    time_over_limit: float
    tiles_focused_on_dust: int
    empty_tiles_frames: float
    seam_error_px: float
    phase_frames_per_tile: float
    tiles_with_phase: int
    tissue_tiles: int
    empty_tiles: int
    dust_tiles: int


def combine(parts: list[dict[str, Any]]) -> SlideScore:
    """One strategy's score over its slides (each part one slide's scan, scored by
    `slide_scores.scored_scan`)."""

    def total(key: str) -> float:
        return float(sum(part[key] for part in parts))

    imaged, stated = total("tissue_imaged"), total("tissue_risk_stated")
    seams_px = np.array([part["seam_error_px"] for part in parts])
    seams_px = seams_px[np.isfinite(seams_px)]  # a slide of separate fields has no seams
    return SlideScore(
        tissue_in_focus_fraction=total("tissue_in_focus") / max(total("tissue_tiles"), 1.0),
        tissue_stated_in_focus_fraction=(
            1.0 - total("tissue_risk_sum") / stated if stated else float("nan")
        ),
        tissue_mae_um=total("tissue_error_um") / imaged if imaged else float("nan"),
        frames_per_tile=total("frames") / total("tiles"),
        time_over_limit=total("scan_time_s") / total("limit_time_s"),
        tiles_focused_on_dust=int(total("on_dust")),
        empty_tiles_frames=total("empty_frames") / max(total("empty_tiles"), 1.0),
        seam_error_px=float(np.sqrt(np.mean(seams_px**2))) if seams_px.size else float("nan"),
        phase_frames_per_tile=total("phase_frames") / total("tiles"),
        tiles_with_phase=int(total("tiles_with_phase")),
        tissue_tiles=int(total("tissue_tiles")),
        empty_tiles=int(total("empty_tiles")),
        dust_tiles=int(total("dust_tiles")),
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--seeds", type=seed_number, nargs="+", default=[1, 2], help="slides' seeds (1 2)"
    )
    grid_side = whole_number(2, MAX_GRID_SIDE)
    parser.add_argument("--rows", type=grid_side, default=10, help="tile rows, >= 2 (10)")
    parser.add_argument("--cols", type=grid_side, default=10, help="tile columns, >= 2 (10)")
    parser.add_argument(
        "--size",
        type=whole_number(MIN_SIZE_PX, MAX_FRAME_SIDE_PX),
        default=256,
        help=f"frame side in pixels, even, >= {MIN_SIZE_PX} (256)",
    )
    parser.add_argument(  # its range is the simulator's, checked by `slide_problem`
        "--overlap", type=finite_number(), default=0.1, help="tiles' overlap (tissue; 0.1)"
    )
    parser.add_argument(
        "--specimen", default=TISSUE, choices=[TISSUE, *SPECIMENS],
        help="what the slide carries: a virtual tissue section (tissue, the default) or "
        "separate fields of one of the simulator's specimens",
    )  # fmt: skip
    parser.add_argument(
        "--focus-mode", choices=[mode.value for mode in PeakMode],
        help="the focus service's mode (default: valley for the unstained specimens, "
        "phase-*; max otherwise)",
    )  # fmt: skip
    parser.add_argument(
        "--family", default="standard", choices=list(FAMILIES),
        help="map family of the section's (or the fields') heights (standard)",
    )  # fmt: skip
    parser.add_argument(
        "--strategies", nargs="+", default=list(DEFAULT_STRATEGIES), metavar="NAME",
        choices=list(registry.STRATEGIES),
        help=f"strategies (default: {' '.join(DEFAULT_STRATEGIES)})",
    )  # fmt: skip
    parser.add_argument(
        "--phase", action="store_true",
        help="a phase stack of every tile not found empty, reconstructed by a phase service "
        "beside the stack (focustrack scan --phase; for the unstained specimens)",
    )  # fmt: skip
    parser.add_argument(
        "--no-look-first", dest="look_first", action="store_false",
        help="whole first stacks (strategies that take look_first otherwise scan with it)",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=output_folder, default=Path("out/bench-slide"), help="work folder"
    )
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the scores as JSON")


def look_first_params(strategy: str, look_first: bool) -> dict[str, Any]:
    """`strategy`'s parameters in the bench: `look_first` where it takes it."""
    takes = "look_first" in registry.STRATEGIES[strategy].params.model_fields
    return {"look_first": look_first} if takes else {}


def focus_mode(args: argparse.Namespace) -> str:
    """The focus service's mode: `--focus-mode`, or the specimen's own (a phase object is
    faintest in focus: valley)."""
    if args.focus_mode is not None:
        return str(args.focus_mode)
    return (PeakMode.VALLEY if args.specimen.startswith("phase-") else PeakMode.MAX).value


def instrument_arguments(args: argparse.Namespace, seed: int) -> list[str]:
    """The simulated instrument's flags for the slide of `seed`."""
    slide = [
        "--seed", str(seed), "--family", args.family, "--slides", "1", "--rows", str(args.rows),
        "--cols", str(args.cols), "--width", str(args.size), "--height", str(args.size),
    ]  # fmt: skip
    if args.specimen == TISSUE:
        return ["--tissue-slide", "--overlap", str(args.overlap), *slide]
    return ["--specimen", args.specimen, *slide]


def scan_slide(
    stack: LocalStack,
    options: ScanOptions,
    strategy: str,
    scan_dir: Path,
    look_first: bool,
    empty: np.ndarray | None,
) -> dict[str, Any]:
    """Scan the stack's slide with `strategy` (`look_first` where it takes it); the part of
    `combine` it makes (`empty`: a slide of separate fields' bare glass, as `scored_scan`)."""
    request = options.request(INSTRUMENT, SLIDE, strategy, look_first_params(strategy, look_first))
    report = scan_on(stack, options, request, scan_dir, strategy, None)
    assert stack.session is not None
    part = scored_scan(stack.session, INSTRUMENT, SLIDE, scan_dir, report, empty)
    return part | {
        "phase_frames": report["phase_images_acquired"],
        "tiles_with_phase": report["tiles_with_phase"],
    }


def run(args: argparse.Namespace) -> int:
    problem = slide_problem(args)
    if problem is not None:  # said before any stack starts
        print(f"focustrack bench slide: error: {problem}", file=sys.stderr)
        return 2
    options = ScanOptions.defaults(no_progress=True, phase=args.phase)
    parts: dict[str, list[dict[str, Any]]] = {name: [] for name in args.strategies}
    started_s = time.perf_counter()
    mode = focus_mode(args)
    for seed in args.seeds:
        instrument_args = instrument_arguments(args, seed)
        empty = None
        if args.specimen != TISSUE:
            simulator = SimulatorOptions(
                seed=seed, rows=args.rows, cols=args.cols, width=args.size, height=args.size,
                family=args.family, specimen=args.specimen,
            )  # fmt: skip
            empty = bare_glass(simulator, SLIDE)
        work = args.out / f"seed-{seed}"
        with LocalStack(
            work, instrument_args, phase=args.phase, focus_args=("--focus-mode", mode)
        ) as stack:
            for name in args.strategies:
                part = scan_slide(stack, options, name, work / name, args.look_first, empty)
                parts[name].append(part)
                print(
                    f"seed {seed} {name}: {part['tissue_in_focus']}/{part['tissue_tiles']} "
                    f"tissue tiles in focus, {part['frames'] / part['tiles']:.2f} frames/tile, "
                    f"{part['on_dust']} on dust ({time.perf_counter() - started_s:.0f} s)",
                    flush=True,
                )
    scores = {name: combine(runs) for name, runs in parts.items()}
    slides = (
        f"virtual slides, overlap {args.overlap:g}"
        if args.specimen == TISSUE
        else f"{args.specimen} slides, focus mode {mode}"
    )
    title = (
        f"{slides}, seeds {' '.join(map(str, args.seeds))}: {args.rows}x{args.cols} "
        f"tiles of {args.size} px, family {args.family}"
        f"{'' if args.look_first else ', without look_first'}"
        f"{', a phase stack on every tile not found empty' if args.phase else ''}"
    )
    print(format_scores(title, scores))
    if args.json is not None:
        report = {
            "title": title,
            "specimen": args.specimen,
            "focus_mode": mode,
            "scores": {name: asdict(s) for name, s in scores.items()},
        }
        write_json(args.json, report)
        print(f"wrote {args.json}")
        figure(scores, args.json.with_suffix(".png"), title)
    return 0


def format_scores(title: str, scores: dict[str, SlideScore]) -> str:
    """One row per strategy."""
    header = (
        f"{'strategy':<18}{'tissue in focus':>16}{'stated':>8}{'MAE um':>8}{'frames/tile':>12}"
        f"{'/ limit':>9}"
        f"{'on dust':>9}{'empty fr':>10}{'seam px':>9}"
    )
    lines = [title, header, "-" * len(header)]
    for name, s in scores.items():
        phase = (  # with --phase: its frames and the tiles whose phase came back
            f"  phase: {s.phase_frames_per_tile:.2f} frames/tile, {s.tiles_with_phase} tiles"
            if s.phase_frames_per_tile
            else ""
        )
        lines.append(
            f"{name:<18}{s.tissue_in_focus_fraction:>16.1%}"
            f"{s.tissue_stated_in_focus_fraction:>8.1%}{s.tissue_mae_um:>8.3f}"
            f"{s.frames_per_tile:>12.2f}{s.time_over_limit:>9.2f}{s.tiles_focused_on_dust:>9d}"
            f"{s.empty_tiles_frames:>10.2f}{s.seam_error_px:>9.2f}{phase}"
        )
    first = next(iter(scores.values()))
    lines.append(
        f"tiles: {first.tissue_tiles} tissue, {first.empty_tiles} empty, {first.dust_tiles} "
        "with dust in view"
    )
    return "\n".join(lines)


def figure(scores: dict[str, SlideScore], path: Path, title: str) -> None:
    """Tissue in focus against time over the limit, one point per strategy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, s in scores.items():
        ax.scatter(s.time_over_limit, 100 * s.tissue_in_focus_fraction)
        ax.annotate(name, (s.time_over_limit, 100 * s.tissue_in_focus_fraction), fontsize=8)
    ax.set_xlabel("scan time / physical limit")
    ax.set_ylabel("tissue tiles in focus (%)")
    ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
