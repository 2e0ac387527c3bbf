"""`focustrack bench instrument`: how fast the simulated microscope renders and ships a z-stack.

- Render: a `--frames`-frame stack of `--size` x `--size` RGB pixels, for new tiles
  (cold: specimen drawn and its spectrum taken, then the stack) and for the same tiles
  again (warm: the stack only), with one render thread and with `--workers` (the
  service's default, 2) side by side. Wall and CPU seconds; OpenCV's own threads off.
- Publish: the stack from this process to a subscriber in another process over
  loopback TCP, until the subscriber has decoded it and acknowledged, as the instrument
  sends it (raw pixels as payload, header as attachment) and, for comparison, as one
  protobuf `ZStack` message with the pixels in a bytes field.
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import statistics
import sys
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
import zenoh

from focustrack.arguments import count_number, output_file, seed_number, whole_number
from focustrack.bench.json_report import write_json
from focustrack_core.surfaces import SurfaceSpec
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import codec, keys, session
from focustrack_instrument_sim.microscope import (
    Microscope,
    MicroscopeSpec,
    slides_from_seed,
)
from focustrack_instrument_sim.simulator_options import MAX_FRAME_SIDE_PX

ACK_KEY = keys.bench_key("ack")
MESSAGE_KEY = keys.bench_key("zstack-message")
RAW_PATTERN = keys.zstack_pattern("bench")


#: The most render threads compared with one (more than a machine's cores show nothing more).
MAX_WORKERS = 256


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--size",
        type=whole_number(1, MAX_FRAME_SIDE_PX),
        default=1024,
        help="frame side in pixels, even",
    )
    parser.add_argument(
        "--frames",
        type=whole_number(1, MicroscopeSpec.max_frames),  # the most the microscope takes
        default=21,
        help=f"frames per stack, at most {MicroscopeSpec.max_frames}",
    )
    parser.add_argument(
        "--stacks", type=count_number, default=5, help="stacks rendered (cold and warm)"
    )
    parser.add_argument(
        "--workers",
        type=whole_number(1, MAX_WORKERS),
        default=2,
        help=f"render threads to compare with 1, at most {MAX_WORKERS}",
    )
    parser.add_argument(
        "--repeats", type=count_number, default=10, help="stacks published per encoding"
    )
    parser.add_argument("--seed", type=seed_number, default=0)
    parser.add_argument("--json", type=output_file, help="write the figures to this JSON file")


def _timed(action: Callable[[], object]) -> tuple[float, float]:
    """(wall, CPU) seconds of `action()`."""
    wall, cpu = time.perf_counter(), time.process_time()
    action()
    return time.perf_counter() - wall, time.process_time() - cpu


def bench_render(size: int, n_frames: int, n_stacks: int, seed: int, workers: int) -> dict:
    """Median wall and CPU seconds per stack, cold (new tile) and warm (same tile again),
    with `workers` render threads."""
    spec = MicroscopeSpec(height=size, width=size, cached_tiles=n_stacks, workers=workers)
    side = int(np.ceil(np.sqrt(n_stacks)))
    scope = Microscope(slides_from_seed(seed, 1, SurfaceSpec(side, side)), spec, seed=seed)
    truth_um, _ = scope.truth_um("slide-0")
    tiles = [divmod(i, side) for i in range(n_stacks)]
    results: dict[str, list[tuple[float, float]]] = {"cold": [], "warm": []}
    for phase in ("cold", "warm"):
        for row, col in tiles:
            z_low = truth_um[row, col] - (n_frames - 1) / 2 * 0.5
            results[phase].append(
                _timed(functools.partial(scope.acquire, "slide-0", row, col, z_low, 0.5, n_frames))
            )
            print(f"render {phase} tile ({row}, {col}), {workers} thread(s): "
                  f"{results[phase][-1][0]:.3f} s", flush=True)  # fmt: skip
    scope.close()
    return {
        f"render_{workers}t_{phase}_{kind}_s": statistics.median(t[i] for t in timings)
        for phase, timings in results.items()
        for i, kind in enumerate(("wall", "cpu"))
    }


def _subscriber(endpoint: str) -> None:
    """Child process: decode every stack it receives and acknowledge it."""
    with session.open_session(connect=[endpoint]) as child:

        def on_raw(sample: zenoh.Sample) -> None:
            header, pixels = codec.decode_zstack_sample(sample)
            child.put(ACK_KEY, f"raw {header.sequence} {int(pixels[-1, -1, -1, -1])}")

        def on_message(sample: zenoh.Sample) -> None:
            header, pixels = codec.decode_zstack_message(sample.payload.to_bytes())
            child.put(ACK_KEY, f"message {header.sequence} {int(pixels[-1, -1, -1, -1])}")

        with (
            child.declare_subscriber(RAW_PATTERN, on_raw),
            child.declare_subscriber(MESSAGE_KEY, on_message),
        ):
            child.put(ACK_KEY, "ready")
            threading.Event().wait()  # until the parent terminates this process


def bench_publish(pixels: np.ndarray, repeats: int) -> dict:
    """Median ms from encoding a stack to its decoded acknowledgement, for both encodings."""
    endpoint = session.loopback_endpoint()
    acks: list[str] = []
    arrived = threading.Condition()

    def on_ack(sample: zenoh.Sample) -> None:
        with arrived:
            acks.append(sample.payload.to_string())
            arrived.notify_all()

    def wait_for(prefix: str) -> None:
        with arrived:
            if not arrived.wait_for(lambda: any(a.startswith(prefix) for a in acks), 60):
                raise TimeoutError(f"no acknowledgement {prefix!r} from the subscriber")
            acks.clear()

    z_um = list(np.arange(pixels.shape[0]) * 0.5)
    block = zenoh.CongestionControl.BLOCK
    with session.open_session(listen=[endpoint]) as parent:
        parent.declare_subscriber(ACK_KEY, on_ack)
        child = multiprocessing.get_context("spawn").Process(target=_subscriber, args=(endpoint,))
        child.start()
        try:
            wait_for("ready")
            time.sleep(0.5)  # the child's subscriptions reach this session
            times_ms: dict[str, list[float]] = {"raw": [], "message": []}
            for sequence in range(repeats):
                header = instrument_pb2.ZStackHeader(slide="bench", sequence=sequence, z_um=z_um)
                started = time.perf_counter()
                payload, attachment = codec.encode_zstack(header, pixels)
                parent.put(keys.zstack_key("bench", 0, 0), payload, attachment=attachment,
                           congestion_control=block)  # fmt: skip
                wait_for(f"raw {sequence} ")
                times_ms["raw"].append(1e3 * (time.perf_counter() - started))
                started = time.perf_counter()
                parent.put(MESSAGE_KEY, codec.encode_zstack_message(header, pixels),
                           congestion_control=block)  # fmt: skip
                wait_for(f"message {sequence} ")
                times_ms["message"].append(1e3 * (time.perf_counter() - started))
                print(f"publish {sequence}: raw {times_ms['raw'][-1]:.1f} ms, "
                      f"message {times_ms['message'][-1]:.1f} ms", flush=True)  # fmt: skip
        finally:
            child.terminate()
            child.join()
    results = {}
    for name, label in (("raw", "raw_attachment"), ("message", "protobuf_bytes_field")):
        median_ms = statistics.median(times_ms[name])
        results[f"publish_{label}_ms"] = median_ms
        results[f"publish_{label}_gb_per_s"] = pixels.nbytes / (median_ms * 1e-3) / 1e9
    return results


def run(args: argparse.Namespace) -> int:
    if args.size % 2:  # the simulator's frames have even sides (a traceback at the first)
        print(
            f"focustrack bench instrument: error: --size must be even, got {args.size}",
            file=sys.stderr,
        )
        return 2
    cv2.setNumThreads(1)  # threads are the renderer's own, not OpenCV's
    figures: dict = {"size": args.size, "frames": args.frames}
    for workers in sorted({1, args.workers}):
        figures.update(bench_render(args.size, args.frames, args.stacks, args.seed, workers))
    pixels = np.random.default_rng(args.seed).integers(
        0, 4096, size=(args.frames, args.size, args.size, 3), dtype=np.uint16
    )
    figures["stack_mb"] = pixels.nbytes / 1e6
    figures.update(bench_publish(pixels, args.repeats))
    print(f"\n{args.frames}-frame {args.size}x{args.size} RGB stack ({figures['stack_mb']:.0f} MB)")
    for workers in sorted({1, args.workers}):
        for phase in ("cold", "warm"):
            name = f"render_{workers}t_{phase}"
            print(f"  render {phase:4s}, {workers} thread(s): {figures[f'{name}_wall_s']:.3f} s "
                  f"wall, {figures[f'{name}_cpu_s']:.3f} s CPU")  # fmt: skip
    for label in ("raw_attachment", "protobuf_bytes_field"):
        print(f"  publish to another process, {label}: {figures[f'publish_{label}_ms']:.1f} ms "
              f"({figures[f'publish_{label}_gb_per_s']:.2f} GB/s)")  # fmt: skip
    if args.json:
        write_json(args.json, figures)
    return 0
