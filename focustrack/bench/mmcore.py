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
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pymmcore_plus import CMMCorePlus

from focustrack_instrument_sim.instrument import StackRequest
from focustrack_instrument_sim.mmcore_backend import MMCoreInstrument, core_from_config
from focustrack_instrument_sim.mmcore_options import MMCoreOptions

#: The overhead per plane the backend should stay under, ms.
TARGET_OVERHEAD_MS = 2.0
Z_STEP_UM = 0.5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=21, help="planes per stack")
    parser.add_argument("--stacks", type=int, default=10, help="stacks per kind and mode")
    parser.add_argument("--exposure-ms", type=float, default=1.0, help="exposure per plane")
    parser.add_argument(
        "--mm-config", type=Path, help="a Micro-Manager configuration (default: the demo's)"
    )
    parser.add_argument(
        "--mm-adapter-path", type=Path, nargs="*", default=[], help="device adapter folders"
    )
    parser.add_argument("--json", type=Path, help="write the figures to this JSON file")


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


def run(args: argparse.Namespace) -> int:
    if args.frames < 1 or args.stacks < 1 or not args.exposure_ms > 0:
        print("--frames and --stacks must be at least 1, --exposure-ms positive")
        return 2
    if args.mm_config is None:
        try:
            config, adapters = _demo()
        except ImportError:
            print("the demo devices need mm-test-adapters (pip install mm-test-adapters), or "
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
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(figures, indent=2))
    return 0
