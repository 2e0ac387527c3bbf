"""`focustrack bench mmcore`: what the MMCore backend costs per plane over bare MMCore calls.

On one core (by default Micro-Manager's demo devices from `mm-test-adapters`), stacks
are taken alternately by bare pymmcore-plus calls and by the backend's `acquire`, side
by side in one run, and timed per plane:

- snapped: bare `setPosition`, `waitForDevice`, `snapImage`, `getImage` per plane,
  against `MMCoreInstrument.acquire` of a plan that snaps (its z read-back, bounded
  snap and copy into the shell's buffer included);
- sequenced, where the focus device can sequence (the demo's DStage with UseSequences):
  bare `loadStageSequence`, `startStageSequence`, `startSequenceAcquisition` and
  `popNextImage` until the stack is in, against the backend's sequenced `acquire`.

The backend's XY move (its `plan`) is not timed: the bare loop has none. The shutter
stays as it is (auto-shutter off) so both do the same device work, and the demo camera
reuses its image (FastImage) so that its drawing does not drown the difference.

Then (unless `--no-scan`) one slide is scanned through every service (router, instrument,
focus service, estimator, scheduler) twice, side by side: with the simulator
(`--backend sim`) and with the same simulated slide behind Micro-Manager's device layer
(`--backend mmcore-sim`: pymmcore-plus Python devices served by the MMCore backend). The
frames are the same, so frames per tile, the in-focus share and the MAE should agree
within the noise; the wall time says what the device path costs in a scan.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pymmcore_plus import CMMCorePlus

from focustrack.arguments import (
    count_number,
    output_file,
    output_folder,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench.json_report import write_json
from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack, stop_on_sigterm
from focustrack_core.geometry import MAX_GRID_SIDE
from focustrack_estimator import registry
from focustrack_instrument_sim.instrument import StackRequest
from focustrack_instrument_sim.mmcore_backend import MMCoreInstrument, core_from_config
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
from focustrack_instrument_sim.simulator_options import MAX_FRAME_SIDE_PX
from focustrack_scheduler.scan import ScanJob, run_scan
from focustrack_scheduler.settings import ScanOptions

#: The overhead per plane the backend should stay under, ms.
TARGET_OVERHEAD_MS = 2.0
Z_STEP_UM = 0.5
#: The backends a slide is scanned with, side by side.
SCAN_BACKENDS = ("sim", "mmcore-sim")
#: What a scan's report says that the comparison shows.
SCAN_FIGURES = ("images_per_tile", "in_focus_fraction", "mae_um", "scan_time_s")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=count_number, default=21, help="planes per stack")
    parser.add_argument("--stacks", type=count_number, default=10, help="stacks per kind and mode")
    parser.add_argument(
        "--exposure-ms", type=positive_float, default=1.0, help="exposure per plane"
    )
    parser.add_argument(
        "--mm-config", type=Path, help="a Micro-Manager configuration (default: the demo's)"
    )
    parser.add_argument(
        "--mm-adapter-path", type=Path, nargs="*", default=[], help="device adapter folders"
    )
    parser.add_argument("--no-scan", action="store_true", help="time the planes only")
    # the demo's slide (`focustrack demo`), so that the figures compare with its table
    grid_side = whole_number(1, MAX_GRID_SIDE)
    parser.add_argument("--rows", type=grid_side, default=10, help="tiles per column of the slide")
    parser.add_argument("--cols", type=grid_side, default=10, help="tiles per row of the slide")
    parser.add_argument(
        "--size", type=whole_number(1, MAX_FRAME_SIDE_PX), default=512, help="frame side, px"
    )
    parser.add_argument("--seed", type=seed_number, default=1, help="the slide's seed")
    parser.add_argument(
        "--strategy",
        default="kf-2d-lean",
        choices=list(registry.STRATEGIES),
        help="the scan's strategy",
    )
    parser.add_argument(
        "--out", type=output_folder, default=Path("out/bench-mmcore"), help="the scans' work folder"
    )
    parser.add_argument("--json", type=output_file, help="write the figures to this JSON file")


def _demo() -> tuple[Path, list[Path]]:
    """The demo configuration and its adapters (mm-test-adapters, a development dependency)."""
    import mm_test_adapters

    adapters = Path(mm_test_adapters.device_adapter_path())
    return adapters / "MMConfig_demo.cfg", [adapters]


def _open(config: Path, adapters: list[Path], sequenced: bool) -> CMMCorePlus:
    core = core_from_config(config, adapters)
    camera, focus = core.getCameraDevice(), core.getFocusDevice()
    core.setAutoShutter(False)
    if core.hasProperty(camera, "FastImage"):  # the demo camera: no drawing per image
        core.setProperty(camera, "FastImage", "1")
    if sequenced and core.hasProperty(focus, "UseSequences"):  # the demo stage: sequences
        core.setProperty(focus, "UseSequences", "Yes")
    return core


def _bare_snaps(core: CMMCorePlus, z_um: np.ndarray) -> None:
    focus = core.getFocusDevice()
    for z in z_um:
        core.setPosition(focus, float(z))
        core.waitForDevice(focus)
        core.snapImage()
        core.getImage()


def _bare_sequence(core: CMMCorePlus, z_um: np.ndarray) -> None:
    focus = core.getFocusDevice()
    core.loadStageSequence(focus, [float(z) for z in z_um])
    core.startStageSequence(focus)
    core.startSequenceAcquisition(len(z_um), 0.0, True)
    popped = 0
    while popped < len(z_um):
        if core.getRemainingImageCount() > 0:
            core.popNextImage()
            popped += 1
        else:
            time.sleep(0.0002)  # as the backend polls
    core.stopStageSequence(focus)


def bench_mode(
    config: Path, adapters: list[Path], sequenced: bool, n_frames: int, n_stacks: int,
    exposure_ms: float,
) -> dict[str, float] | None:  # fmt: skip
    """Median ms per plane of bare calls and of the backend, stacks taken alternately; None
    when `sequenced` and the focus device cannot sequence."""
    core = _open(config, adapters, sequenced)
    options = MMCoreOptions(
        mm_z_min_um=-1000.0, mm_z_max_um=1000.0, mm_sequence=sequenced, mm_max_frames=n_frames
    )
    instrument = MMCoreInstrument(core, options)
    mode = "sequenced" if sequenced else "snapped"
    try:
        if sequenced and not instrument.sequenced:
            print(f"{mode}: the focus device {instrument.focus!r} cannot sequence; skipped")
            return None
        request = StackRequest("slide-0", 0, 0, 0.0, Z_STEP_UM, n_frames, exposure_ms / 1000.0)
        plan = instrument.plan(request)  # tile (0, 0): where the stage stands
        buffers = [np.empty(plan.frame.shape, plan.frame.dtype) for _ in range(n_frames)]
        core.setExposure(exposure_ms)  # the bare loop's exposure too
        bare_run = _bare_sequence if sequenced else _bare_snaps
        runs: dict[str, Callable[[], object]] = {
            "bare": lambda: bare_run(core, plan.z_um),
            "backend": lambda: sum(1 for _ in instrument.acquire(plan, buffers.__getitem__)),
        }
        per_plane_ms: dict[str, list[float]] = {name: [] for name in runs}
        for stack in range(n_stacks + 1):  # the first of each is a warm-up
            for name, run in runs.items():
                started = time.perf_counter()
                run()
                if stack:
                    per_plane_ms[name].append(1e3 * (time.perf_counter() - started) / n_frames)
            if stack:
                bare_ms, backend_ms = per_plane_ms["bare"][-1], per_plane_ms["backend"][-1]
                print(f"{mode} stack {stack}/{n_stacks}: bare {bare_ms:.2f}, backend "
                      f"{backend_ms:.2f} ms/plane", flush=True)  # fmt: skip
    finally:
        instrument.close()
    bare_ms = statistics.median(per_plane_ms["bare"])
    backend_ms = statistics.median(per_plane_ms["backend"])
    return {
        "bare_ms_per_plane": bare_ms,
        "backend_ms_per_plane": backend_ms,
        "overhead_ms_per_plane": backend_ms - bare_ms,
    }


def scan_backends(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """The figures of one scan of the same slide with each of `SCAN_BACKENDS`, each on a
    local stack of its own (the scan's report, and its wall time, s)."""
    figures: dict[str, dict[str, Any]] = {}
    for backend in SCAN_BACKENDS:
        work = args.out / backend
        shutil.rmtree(work, ignore_errors=True)  # a fresh slide and estimator each run
        instrument_args = [
            "--backend", backend, "--seed", str(args.seed), "--slides", "1",
            "--rows", str(args.rows), "--cols", str(args.cols),
            "--width", str(args.size), "--height", str(args.size),
        ]  # fmt: skip
        with LocalStack(work, instrument_args) as stack:
            assert stack.session is not None
            job = ScanJob(
                request=ScanOptions.defaults().request(INSTRUMENT, SLIDE, args.strategy),
                estimator_url=stack.estimator_url,
                out_dir=work / "scan",
                label=f"{args.strategy} on --backend {backend}",
                trust=stack.trust,
            )
            started_s = time.perf_counter()
            report = run_scan(stack.session, job)
            wall_s = time.perf_counter() - started_s
        figures[backend] = {name: report[name] for name in SCAN_FIGURES} | {"wall_s": wall_s}
    return figures


def scan_table(figures: dict[str, dict[str, Any]]) -> str:
    """The scans' figures side by side, a row per backend (markdown)."""
    lines = [
        "| backend | frames/tile | in focus | MAE um | simulated scan s | wall s |",
        "|---|---|---|---|---|---|",
    ]
    for backend, scan in figures.items():
        lines.append(
            f"| {backend} | {scan['images_per_tile']:.2f} | {scan['in_focus_fraction']:.1%} | "
            f"{scan['mae_um']:.3f} | {scan['scan_time_s']:.1f} | {scan['wall_s']:.1f} |"
        )
    return "\n".join(lines)


def _error(message: str) -> None:
    print(f"focustrack bench mmcore: error: {message}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    if args.mm_config is None:
        try:
            config, adapters = _demo()
        except ImportError:
            _error("the demo devices need mm-test-adapters (pip install mm-test-adapters), or "
                   "give --mm-config and --mm-adapter-path")  # fmt: skip
            return 2
    else:
        config, adapters = args.mm_config, args.mm_adapter_path
    figures: dict = {
        "config": str(config),
        "frames": args.frames,
        "stacks": args.stacks,
        "exposure_ms": args.exposure_ms,
        "target_overhead_ms_per_plane": TARGET_OVERHEAD_MS,
    }
    for mode, sequenced in (("snapped", False), ("sequenced", True)):
        figures[mode] = bench_mode(
            config, adapters, sequenced, args.frames, args.stacks, args.exposure_ms
        )
    print(f"\n{args.frames}-plane stacks, {args.exposure_ms:g} ms exposure, median of "
          f"{args.stacks} stacks each")  # fmt: skip
    print("| mode | bare MMCore ms/plane | backend ms/plane | overhead ms/plane |")
    print("|---|---|---|---|")
    for mode in ("snapped", "sequenced"):
        measured = figures[mode]
        if measured is None:
            print(f"| {mode} | - | - | - (the focus device does not sequence) |")
            continue
        print(f"| {mode} | {measured['bare_ms_per_plane']:.2f} | "
              f"{measured['backend_ms_per_plane']:.2f} | "
              f"{measured['overhead_ms_per_plane']:+.2f} |")  # fmt: skip
    if not args.no_scan:
        stop_on_sigterm()  # so that the stacks' processes are stopped on the way out
        print(f"\nscanning a {args.rows}x{args.cols} slide (seed {args.seed}, "
              f"{args.size} px) with {args.strategy} on each backend", flush=True)  # fmt: skip
        figures["scan"] = {
            "rows": args.rows, "cols": args.cols, "size_px": args.size, "seed": args.seed,
            "strategy": args.strategy,
        } | scan_backends(args)  # fmt: skip
        print(scan_table({backend: figures["scan"][backend] for backend in SCAN_BACKENDS}))
    if args.json:
        write_json(args.json, figures)
    return 0
