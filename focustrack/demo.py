"""`focustrack demo`: the whole product on loopback, and a comparison of scan strategies.

Starts a Zenoh router in this process and the instrument, focus and estimator
services as separate processes (`python -m focustrack serve ...`) on free ports,
waits until each answers, then scans the same simulated slide (with `--tissue-slide`,
a virtual slide: one tissue section with empty glass, holes, a fold, tilt and coverslip
dust, cut into tiles that overlap by `--overlap`; `make demo` scans it) once per strategy
(the best Kalman filter, the same with the lean risk rule measuring with pairs of
frames, kf-2d-laser reading the instrument's laser autofocus on every tile, Delaunay
focus-map surveying and autofocus on every tile by default; then a second pass of
kf-rescan with the lean scan's map after the slide's focus moved by 12 um) and prints,
per strategy, images per tile, simulated scan time, in-focus fraction and MAE against
the instrument's truth (on a virtual slide, the tissue tiles in focus too), and where
the wall time went. While it scans it serves the live web view of the scan and
prints its address; at the end it saves a screenshot of it (live_view.png, where
chromium is installed; not with `--no-screenshot`), and each scan's mosaic is an
OME-Zarr (`--mosaic-format ome-tiff` for the OME-TIFF). A service that dies is
started again, and the demo says so; the instrument tags its frames and the focus
service its results with keys made for the run, the focus service scores only tagged
frames and the scans take only tagged results (docs/security.md). With ``--phase`` a
phase pass follows on a stack of its own: a 4x4 slide of unstained red cells, its focus
service looking for the contrast minimum, the phase service reconstructing a phase stack
centred on each tile's predicted focus; a line after the table says how many tiles came
out in focus and with phase, and how well their phase correlates with the true phase
(docs/phase.md).
Everything is shut down on the way out, also on Ctrl-C.

    focustrack demo [--rows 10 --cols 10 --size 512] [--strategies A B ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from focustrack.arguments import output_file, output_folder
from focustrack.bench.phase import high_pass_correlation
from focustrack.browser import NoBrowserError, screenshot_live_view
from focustrack.local_stack import INSTRUMENT, READY_TIMEOUT_S, SLIDE, LocalStack, stop_on_sigterm
from focustrack.slide_scores import scored_scan
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.surfaces import FAMILIES
from focustrack_core.timing import TimingModel
from focustrack_core.wire.session import SHARED_MEMORY_MB, shared_memory_room_mb
from focustrack_estimator import registry
from focustrack_estimator.replay import limit_time_s
from focustrack_instrument_sim.phase_specimen import GLASS_PHASE_RAD
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_scheduler.clients import wait_for_instrument
from focustrack_scheduler.live_view import LiveServer, port_number
from focustrack_scheduler.outputs import (
    FOCUS_MAP_NPY,
    MOSAIC_ZARR,
    PHASE,
    SCAN_FILES,
    WallTimes,
)
from focustrack_scheduler.plan import ScanRequest
from focustrack_scheduler.scan import SCAN_ERRORS, ScanJob, run_scan
from focustrack_scheduler.settings import BEST_KALMAN, ScanOptions

log = logging.getLogger(__name__)

#: The screenshot of the live view the demo leaves in its output folder.
LIVE_VIEW_PNG = "live_view.png"
LEAN = "kf-2d-lean"
#: The reflection autofocus (the instrument's laser sensor reads the coverslip on each tile).
LASER = "kf-2d-laser"
DEFAULT_STRATEGIES = (BEST_KALMAN, LEAN, LASER, "survey-delaunay", "af-every-tile")
#: The demo's lean scan measures a tile with a pair of frames where the rule takes a short
#: stack (`short_frames` 2: the focus service reads the pair with the slide's learnt curve);
#: the laser scan measures with pairs too. Both look first (`look_first`): a tile of glass
#: costs one frame, and on tissue the look is the pair's lower frame, so it costs nothing
#: there (docs/benchmarks.md, the demo's slide).
STRATEGY_PARAMS: dict[str, dict[str, Any]] = {
    LEAN: {"short_frames": 2, "look_first": True},
    LASER: {"short_frames": 2, "look_first": True},
}
#: The second pass: kf-rescan with the first pass's map, after the slide's focus moved by
#: RESCAN_OFFSET_UM (10 minutes of drift at 0.02 um/s).
RESCAN = "kf-rescan"
SECOND_PASS = "2nd pass kf-rescan"
PHASE_PASS = "phase-pass"
RESCAN_OFFSET_UM = 12.0


def comparison_table(reports: dict[str, dict[str, Any]], limit_s: float) -> str:
    """Images per tile, simulated scan time (also over `limit_s`, the physical limit: stage
    moves and one frame per tile), in-focus fraction (and as the estimator predicted it) and
    MAE of each strategy; on a virtual slide (reports with `tissue_tiles`), the tissue tiles
    in focus too (`tissue_scores`)."""

    def number(value: float | None, form: str) -> str:
        return "n/a" if value is None else format(value, form)

    tissue = any("tissue_tiles" in report for report in reports.values())
    header = (
        f"{'strategy':<18}{'images/tile':>12}{'scan time s':>13}{'/ limit':>9}{'in focus':>10}"
        f"{'predicted':>11}{'MAE um':>9}" + (f"{'tissue':>9}" if tissue else "")
    )
    lines = [header, "-" * len(header)]
    for name, report in reports.items():
        tissue_cell = (
            f"{report['tissue_in_focus']}/{report['tissue_tiles']}"
            if "tissue_tiles" in report
            else "n/a"
        )
        lines.append(
            f"{name:<18}{report['images_per_tile']:>12.2f}{report['scan_time_s']:>13.1f}"
            f"{report['scan_time_s'] / limit_s:>9.2f}"
            f"{number(report['in_focus_fraction'], '.1%'):>10}"
            f"{number(report['predicted_in_focus_fraction'], '.1%'):>11}"
            f"{number(report['mae_um'], '.3f'):>9}" + (f"{tissue_cell:>9}" if tissue else "")
        )
    lines.append(f"physical limit (stage moves and one frame per tile): {limit_s:.1f} s")
    lines.append("predicted: in focus as the estimator expected (1 - the mean out-of-focus risk)")
    if tissue:
        lines.append(
            "tissue: tissue tiles (not empty glass) with a kept frame within half the depth of "
            "field of the section or a fold's upper layer, by the instrument's truth"
        )
    return "\n".join(lines)


def tissue_scores(stack: LocalStack, scan_dir: Path, report: dict[str, Any]) -> dict[str, int]:
    """The tissue tiles in focus of the scan of the stack's virtual slide in `scan_dir` (its
    `report`), and how many there are (`slide_scores.scored_scan`)."""
    assert stack.session is not None
    part = scored_scan(stack.session, INSTRUMENT, SLIDE, scan_dir, report)
    return {"tissue_in_focus": part["tissue_in_focus"], "tissue_tiles": part["tissue_tiles"]}


def wall_time_table(reports: dict[str, dict[str, Any]]) -> str:
    """Where each scan's wall time went, in seconds, and the share of all scans together (the
    phase stacks' where scans took some)."""
    parts = [
        ("rendering_s", "render"),
        ("transport_s", "transport"),
        ("focus_computation_s", "focus"),
        ("estimation_s", "estimate"),
        ("waiting_s", "waiting"),
        ("scheduler_s", "scheduler"),
        ("total_s", "total"),
    ]
    if any(report["wall_time_s"]["phase_s"] for report in reports.values()):  # --phase
        parts.insert(-2, ("phase_s", "phase"))
    header = f"{'wall time s':<18}" + "".join(f"{label:>11}" for _, label in parts)
    lines = [header, "-" * len(header)]
    sums = WallTimes().as_dict()
    for name, report in reports.items():
        wall = report["wall_time_s"]
        lines.append(f"{name:<18}" + "".join(f"{wall[key]:>11.1f}" for key, _ in parts))
        for key in sums:
            sums[key] += wall[key]
    total_s = sums["total_s"] or 1.0
    lines.append(
        f"{'share of all':<18}" + "".join(f"{sums[key] / total_s:>11.1%}" for key, _ in parts)
    )
    return "\n".join(lines)


def scan_on(
    stack: LocalStack,
    options: ScanOptions,
    request: ScanRequest,
    scan_dir: Path,
    label: str,
    live: LiveServer | None,
) -> dict[str, Any]:
    """Run one scan of `request` on the stack (outputs in `scan_dir`, a previous scan's there
    removed first); its report."""
    assert stack.session is not None
    _clear(scan_dir)
    job = ScanJob(
        request=request,
        estimator_url=stack.estimator_url,
        out_dir=scan_dir,
        retry=options.retry(),
        progress=not options.no_progress,
        label=label,
        mosaic_format=options.mosaic_format,
        live=live,
        trust=stack.trust,
    )
    return run_scan(stack.session, job)


#: The demo's phase pass: a slide of unstained red cells (phase objects) this size, in tiles.
PHASE_PASS_TILES = 4
PHASE_PASS_SPECIMEN = "phase-blood"


@dataclass(frozen=True)
class PhaseScores:
    """The phase pass against the simulator's truth, one value per tile with phase.

    correlations: of the tile's phase with the true phase, periods over about 6 um
        removed (`focustrack.bench.phase.high_pass_correlation`); none for a tile of bare
        glass (its true phase is 0 throughout: nothing to correlate with).
    glass_rad: the tile's mean phase (rad) where the slide is empty glass (true phase 0):
        zero when the phase is anchored to the background, as the services do by default.
    bare_glass_tiles: tiles with phase and no cell in view.
    """

    correlations: list[float]
    glass_rad: list[float]
    bare_glass_tiles: int


def phase_pass(
    args: argparse.Namespace, options: ScanOptions, out_dir: Path, live: LiveServer | None
) -> tuple[dict[str, Any], PhaseScores]:
    """The demo's own phase pass: a small slide of unstained red cells on a stack of its own
    whose focus service looks for the contrast minimum (a phase object is faintest in
    focus), scanned with kf-2d-lean and a phase stack on every tile. Returns the report
    and how each tile's phase compares with the simulator's true phase."""
    simulator = SimulatorOptions(
        seed=args.seed, slides=1, rows=PHASE_PASS_TILES, cols=PHASE_PASS_TILES,
        width=args.size, height=args.size, specimen=PHASE_PASS_SPECIMEN,
    )  # fmt: skip
    instrument_args = [
        "--seed", str(args.seed), "--slides", "1", "--rows", str(PHASE_PASS_TILES),
        "--cols", str(PHASE_PASS_TILES), "--width", str(args.size), "--height", str(args.size),
        "--specimen", PHASE_PASS_SPECIMEN,
    ]  # fmt: skip
    scan_dir = out_dir / PHASE_PASS
    with LocalStack(
        out_dir / "phase-stack", instrument_args, phase=True,
        focus_args=("--focus-mode", "valley"),
    ) as stack:  # fmt: skip
        request = options.request(INSTRUMENT, SLIDE, LEAN)
        report = scan_on(stack, options, request, scan_dir, PHASE_PASS, live)
    correlations: list[float] = []
    glass_rad: list[float] = []
    bare_glass_tiles = 0
    scope = microscope_from_options(simulator)
    try:
        for row in range(PHASE_PASS_TILES):
            for col in range(PHASE_PASS_TILES):
                file = scan_dir / PHASE / f"r{row}_c{col}.npy"
                if not file.exists():
                    continue
                phase_rad = np.load(file)[0].astype(np.float64)
                true_rad = scope.true_phase(SLIDE, row, col).phase_rad
                glass = np.abs(true_rad) < GLASS_PHASE_RAD
                if glass.all():
                    bare_glass_tiles += 1
                else:
                    correlations.append(high_pass_correlation(phase_rad, true_rad))
                if glass.any():
                    glass_rad.append(float(np.mean(phase_rad[glass])))
    finally:
        scope.close()
    return report, PhaseScores(correlations, glass_rad, bare_glass_tiles)


def phase_line(report: dict[str, Any], scores: PhaseScores) -> str:
    """One line on the phase pass: tiles in focus and with phase, phase frames, accuracy."""
    tiles = report["rows"] * report["cols"]
    in_focus = round(report["in_focus_fraction"] * tiles)
    accuracy = "no phase to compare"
    if scores.correlations:
        accuracy = (
            f"correlation with the true phase median {np.median(scores.correlations):.2f}, "
            f"lowest {min(scores.correlations):.2f}"
        )
    if scores.bare_glass_tiles:
        accuracy += f" ({scores.bare_glass_tiles} of bare glass left out)"
    if scores.glass_rad:
        farthest = max(scores.glass_rad, key=abs)
        accuracy += f"; the glass at {farthest:+.2f} rad at most"
    return (
        f"Phase pass (unstained red cells, {report['rows']}x{report['cols']} tiles, focus at "
        f"the contrast minimum): {in_focus} of {tiles} tiles in focus, "
        f"{report['tiles_with_phase']} with phase, {report['phase_images_acquired']} phase "
        f"frames, {accuracy}"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rows", type=int, default=10, help="tile rows of the slide (10)")
    parser.add_argument("--cols", type=int, default=10, help="tile columns of the slide (10)")
    parser.add_argument("--size", type=int, default=512, help="frame side in pixels (512)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the slide (1)")
    parser.add_argument(
        "--tissue-slide",
        action="store_true",
        help="scan a virtual tissue slide (empty glass, holes, a fold, tilt, coverslip dust, "
        "overlapping tiles) instead of the simulator's slide of independent tiles",
    )
    parser.add_argument(
        "--overlap",
        type=float,
        default=0.1,
        help="with --tissue-slide: share of a tile its neighbours share (0.1)",
    )
    parser.add_argument("--family", choices=list(FAMILIES), default="standard")
    parser.add_argument(
        "--strategies",
        nargs="+",
        metavar="NAME",
        default=list(DEFAULT_STRATEGIES),
        help=f"strategies to compare (default: {' '.join(DEFAULT_STRATEGIES)})",
    )
    parser.add_argument(
        "--out", type=output_folder, default=Path("out/demo"), help="output folder (out/demo)"
    )
    parser.add_argument(
        "--json", type=output_file, metavar="OUT", help="write the comparison as JSON"
    )
    parser.add_argument(
        "--live-port",
        type=port_number,
        default=0,
        help="port of the live web view on 127.0.0.1 (default 0: any free one)",
    )
    parser.add_argument(
        "--rescan-offset-um",
        type=float,
        default=RESCAN_OFFSET_UM,
        help="after the scans, the slide's focus moves by this much (drift between passes) and "
        f"kf-rescan scans it again with the first pass's map (default {RESCAN_OFFSET_UM:g})",
    )
    parser.add_argument("--no-rescan", action="store_true", help="no second pass")
    parser.add_argument(
        "--no-screenshot",
        action="store_true",
        help=f"no {LIVE_VIEW_PNG} at the end (saves starting a headless chromium)",
    )
    parser.add_argument(
        "--shared-memory",
        type=int,
        metavar="MB",
        help="frames cross Zenoh in a shared-memory pool of this many MB, 0: over TCP "
        f"(default {SHARED_MEMORY_MB} when /dev/shm has room for it, else 0)",
    )
    # The options of a scan, as `focustrack scan` has them, from the demo's flags alone.
    ScanOptions.add_arguments(parser, environment=False)


def second_pass(
    stack: LocalStack,
    args: argparse.Namespace,
    options: ScanOptions,
    out_dir: Path,
    first: str,
    live: LiveServer,
) -> dict[str, Any]:
    """Scan the slide again with kf-rescan, the map of strategy `first`'s scan as its prior,
    after moving the slide's focus by `--rescan-offset-um` (the instrument is restarted with
    it: drift between the passes, which kf-rescan is not told)."""
    table = focus_map_of_npy((out_dir / first / FOCUS_MAP_NPY).read_bytes())
    base_um, base_sigma_um = table.posterior_um, table.posterior_sigma_um
    if table.smoothed_um is not None and table.smoothed_sigma_um is not None:
        base_um, base_sigma_um = table.smoothed_um, table.smoothed_sigma_um
    stack.restart_with("instrument", ["--z-offset-um", str(args.rescan_offset_um)])
    scan_dir = out_dir / RESCAN
    params = {
        "prior_map_um": base_um.ravel().tolist(),
        "prior_map_sigma_um": base_sigma_um.ravel().tolist(),
    }
    request = options.request(INSTRUMENT, SLIDE, RESCAN, params)
    return scan_on(stack, options, request, scan_dir, f"{RESCAN} (2nd pass)", live)


def save_screenshot(live_url: str, path: Path) -> None:
    """The last scan's live view as a PNG, for a person to look at (where chromium is)."""
    try:
        print(f"live view screenshot: {screenshot_live_view(live_url, path)}", flush=True)
    except NoBrowserError as error:
        print(f"no live view screenshot: {error}", flush=True)


#: The demo's flag of each of the simulator's options it sets.
_DEMO_FLAGS = {"rows": "--rows", "cols": "--cols", "width": "--size", "height": "--size"}


def slide_problem(args: argparse.Namespace) -> str | None:
    """What the simulated instrument would refuse in the demo's slide (rows, cols, --size,
    --overlap), in the demo's flags; None when it takes it. Said before the stack starts:
    the instrument's refusal used to come as "instrument exited with status 2", with a log
    to read."""
    if args.size < 2 or args.size % 2:
        return f"--size must be even and at least 2, got {args.size}"
    try:
        SimulatorOptions(
            rows=args.rows, cols=args.cols, width=args.size, height=args.size, overlap=args.overlap
        )
    except ValidationError as error:
        problems = []
        for problem in error.errors(include_url=False):
            name = str(problem["loc"][0]) if problem["loc"] else ""
            flag = _DEMO_FLAGS.get(name, f"--{name}")
            message = str(problem["msg"]).removeprefix("Value error, ")
            problems.append(f"{flag}: {message}" if name else message)
        return "; ".join(dict.fromkeys(problems))
    return None


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    names = [name for item in args.strategies for name in item.split(",") if name]
    unknown = [name for name in names if name not in registry.STRATEGIES]
    if args.shared_memory is not None and args.shared_memory < 0:
        print("focustrack demo: error: --shared-memory must be 0 (TCP) or a pool size in MB, "
              f"got {args.shared_memory}", file=sys.stderr)  # fmt: skip
        return 2
    if unknown or not names:
        print(
            f"focustrack demo: error: unknown strategy {', '.join(unknown) or '(none)'}; "
            f"known strategies: {', '.join(registry.STRATEGIES)}",
            file=sys.stderr,
        )
        return 2
    if (problem := slide_problem(args)) is not None:
        print(f"focustrack demo: error: {problem}", file=sys.stderr)
        return 2
    try:
        options = ScanOptions.from_args(args, environment=False)
    except ValueError as error:  # a scan option the settings model refuses
        print(f"focustrack demo: error: {error}", file=sys.stderr)
        return 2
    stop_on_sigterm()
    out_dir: Path = args.out
    out_dir.mkdir(parents=True, exist_ok=True)
    for suffix in ("", "-wal", "-shm"):  # a demo run starts afresh (a stale WAL would replay)
        (out_dir / f"estimator.sqlite{suffix}").unlink(missing_ok=True)
    instrument_args = [
        "--seed", str(args.seed), "--family", args.family, "--slides", "1",
        "--rows", str(args.rows), "--cols", str(args.cols),
        "--width", str(args.size), "--height", str(args.size), "--laser",
    ]  # fmt: skip
    if args.tissue_slide:
        instrument_args += ["--tissue-slide", "--overlap", str(args.overlap)]
    shared_memory_mb = args.shared_memory
    if shared_memory_mb is None:  # the stack is on one host: shared memory where there is room
        shared_memory_mb = SHARED_MEMORY_MB if shared_memory_room_mb() >= SHARED_MEMORY_MB else 0
    path = f"shared memory ({shared_memory_mb} MB pool)" if shared_memory_mb else "TCP loopback"
    kind = f"virtual tissue slide overlapping by {args.overlap:g}" if args.tissue_slide else "slide"
    print(
        f"focustrack demo: a {args.rows}x{args.cols} {kind} of {args.size}x{args.size} px "
        f"tiles (family {args.family}, seed {args.seed}); frames over {path}; outputs in "
        f"{out_dir}",
        flush=True,
    )
    reports: dict[str, dict[str, Any]] = {}
    phased: tuple[dict[str, Any], PhaseScores] | None = None
    # the strategies scan the stained slide without phase stacks; --phase adds a pass of its own
    strategies_options = options.model_copy(update={"phase": False})
    try:
        started_s = time.perf_counter()
        with (
            LocalStack(
                out_dir,
                instrument_args,
                supervise=True,
                shared_memory_mb=shared_memory_mb,
            ) as stack,
            LiveServer(port=args.live_port) as live,
        ):
            assert stack.session is not None
            print(f"services ready in {time.perf_counter() - started_s:.1f} s", flush=True)
            layout = wait_for_instrument(stack.session, INSTRUMENT, READY_TIMEOUT_S).slides[0]
            grid = ScanGrid(layout.rows, layout.cols, layout.pitch_um)
            print(f"live view at {live.url}", flush=True)
            for name in names:
                scan_dir = out_dir / name
                params = STRATEGY_PARAMS.get(name)
                request = strategies_options.request(INSTRUMENT, SLIDE, name, params)
                reports[name] = scan_on(stack, options, request, scan_dir, name, live)
                if args.tissue_slide:
                    reports[name] |= tissue_scores(stack, scan_dir, reports[name])
            if not args.no_rescan:
                first = LEAN if LEAN in reports else names[0]
                print(
                    f"second pass: the slide's focus moved by {args.rescan_offset_um:g} um; "
                    f"{RESCAN} with the map of {first}",
                    flush=True,
                )
                reports[SECOND_PASS] = second_pass(
                    stack, args, strategies_options, out_dir, first, live
                )
                if args.tissue_slide:
                    reports[SECOND_PASS] |= tissue_scores(
                        stack, out_dir / RESCAN, reports[SECOND_PASS]
                    )
            if options.phase:
                print(
                    f"phase pass: a {PHASE_PASS_TILES}x{PHASE_PASS_TILES} slide of unstained red "
                    "cells, a phase stack on every tile",
                    flush=True,
                )
                phased = phase_pass(args, options, out_dir, live)
            if not args.no_screenshot:
                save_screenshot(live.url, out_dir / LIVE_VIEW_PNG)
    except KeyboardInterrupt:
        print("focustrack demo: interrupted; services stopped", file=sys.stderr)
        return 130
    except (*SCAN_ERRORS, RuntimeError, ValueError) as error:
        print(f"focustrack demo: error: {error}", file=sys.stderr)
        return 1
    print()
    print(f"Strategies on the same slide ({args.rows}x{args.cols} tiles, seed {args.seed}):")
    # the slide's tile pitch and the instrument's default timing (`focustrack serve instrument`)
    print(comparison_table(reports, limit_time_s(grid, TimingModel())))
    print()
    print("Where the wall time went (s):")
    print(wall_time_table(reports))
    if phased is not None:
        print(phase_line(*phased))
        print(f"phase of the phase pass: {out_dir / PHASE_PASS / MOSAIC_ZARR} (image `phase`)")
    for name, report in reports.items():
        if report["mosaic"] is not None:
            scan_dir = out_dir / (RESCAN if name == SECOND_PASS else name)
            print(f"mosaic of {name}: {scan_dir / report['mosaic']}")
    if args.json is not None:
        keys = (
            "images_per_tile",
            "scan_time_s",
            "in_focus_fraction",
            "predicted_in_focus_fraction",
            "mae_um",
            "tissue_in_focus",  # on a virtual slide
            "tissue_tiles",
        )
        summary = {
            "strategies": {
                name: {key: report[key] for key in keys if key in report}
                for name, report in reports.items()
            },
            "wall_time_s": {name: report["wall_time_s"] for name, report in reports.items()},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _clear(scan_dir: Path) -> None:
    """Remove a previous demo scan's files (only those a scan writes), so it starts afresh."""
    for name in SCAN_FILES:
        path = scan_dir / name
        if path.is_dir():  # the OME-Zarr mosaic is a folder
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
