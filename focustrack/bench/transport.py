"""`focustrack bench transport`: does the Zenoh path keep up with a modern sCMOS camera?

A parent process publishes z-stacks (`--frames` frames of `--size` x `--size` uint16,
one channel: 21 x 2048 x 2048 = 176 MB by default) frame by frame, as the instrument
does (`codec.PixelPublisher`, frames in buffers of their own), to a subscriber in a
child process, over two paths:

- ``tcp``: loopback TCP, the child's session with shared memory off;
- ``shm``: Zenoh shared memory (the publisher's pool, the child's session with it on).

Transport: the child's consumer thread decodes every frame (the copy out of Zenoh;
over TCP, frames come in parts of `codec.FRAME_PART_BYTES`, copied into the frame)
and notes when it was readable; a stack's transfer time runs from the first frame's
put to the last frame being readable. GB/s and frames/s
are compared with a memcpy of the same bytes (`np.copyto` into a buffer already
written once) measured in the same run.

Ceilings, measured in the same run so that a ratio can be read against what is
possible at all on this machine (`CEILINGS`):

- ``zenoh_tcp``: bare Zenoh sessions over TCP loopback with the same settings, the same
  frames put in the same parts (`codec.frame_parts`), copied out with ``to_bytes()``
  and into a frame, nothing else (no header, no decoding): the most our TCP path can
  reach with zenoh's Python API;
- ``socket_tcp``: a plain TCP socket, ``sendall`` from the frames' own buffers and
  ``recv_into`` a buffer made once (one copy in the kernel each way): what pixels
  reach over loopback outside Zenoh;
- ``two_copies``: two processes copying a stack each at the same time (each path
  copies once on each side, and the two copies share the memory bus): the most any
  path with a copy on each side can reach.

Focus: the child runs the focus service's own frame analyser
(`focustrack_focus.service.FrameAnalyser`) on every frame as it lands, on a consumer
thread fed through a bounded FIFO (as the service is), and reports the time from the
moment Zenoh hands over the last frame (its last part, before its copy) to the focus
result. Frames are paced at `--fps` (a camera's rate), so the figure is the wait a scan
sees once the camera is done, not a backlog of the publisher's burst.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import multiprocessing
import socket
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from focustrack.arguments import (
    MAX_COUNT,
    count_number,
    output_file,
    positive_float,
    whole_number,
)
from focustrack.bench.json_report import write_json
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import codec, keys, session
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.service import FrameAnalyser
from focustrack_instrument_sim.simulator_options import MAX_FRAME_SIDE_PX

TRANSPORT_SLIDE = "bench-transport"  # stacks the child only receives
FOCUS_SLIDE = "bench-focus"  # stacks the child also runs the focus analysis on
ACK_KEY = keys.bench_key("transport-ack")
PATHS = ("tcp", "shm")
CEILINGS = ("zenoh_tcp", "socket_tcp", "two_copies")
CEILING_KEY = keys.bench_key("transport-ceiling")
SOCKET_BUFFER_BYTES = 8 * 1024 * 1024  # as Zenoh's links (session.PIXEL_TUNING)
FRAME_QUEUE = 64  # frames Zenoh hands over before the consumer holds the publisher back

#: The targets (docs/benchmarks.md): checked and printed beside the figures.
TCP_MIN_GB_PER_S = 1.5
TCP_MIN_MEMCPY_RATIO = 1 / 5
SHM_MIN_MEMCPY_RATIO = 1 / 2
FOCUS_MAX_LATENCY_S = 0.020


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--size",
        type=whole_number(1, MAX_FRAME_SIDE_PX),
        default=2048,
        help="frame side in pixels (2048)",
    )
    parser.add_argument(
        "--frames",
        type=whole_number(3, MAX_COUNT),  # the focus run fits a curve to 3 frames at least
        default=21,
        help="frames per stack, >= 3 (21)",
    )
    parser.add_argument("--stacks", type=count_number, default=10, help="stacks sent per path (10)")
    parser.add_argument(
        "--fps", type=positive_float, default=100.0, help="camera frame rate of the focus run (100)"
    )
    parser.add_argument(
        "--json",
        type=output_file,
        metavar="OUT",
        help="write the figures as JSON, and a chart beside it (OUT with .png)",
    )


def _child(endpoint: str, shared_memory: bool) -> None:
    """Subscriber process: acknowledges each stack on TRANSPORT_SLIDE with its frames'
    arrival, and each on FOCUS_SLIDE with its focus result's latency.

    Frames are taken from a bounded FIFO by one consumer thread, as in the focus service
    (`ZenohFocusWorker`): the copy out of Zenoh happens there, so Zenoh's receiving thread
    goes on with the next frame meanwhile.
    """
    with session.open_session(connect=[endpoint], shared_memory=shared_memory) as child:
        arrivals: dict[int, list[float]] = {}
        analyser = FrameAnalyser(FocusSettings(), na=None)

        def acknowledge(report: dict[str, Any]) -> None:
            child.put(ACK_KEY, json.dumps(report))

        transported = codec.FrameAssembler()

        def on_transport_frame(key: str, payload: bytes, attachment: bytes | None) -> None:
            header = codec.zframe_header(attachment)
            frame = transported.add(key, header, payload)
            if frame is None:
                return  # a part of the frame: more to come
            int(frame[-1, -1, -1])  # the pixels are readable where they landed
            times = arrivals.setdefault(header.stack.sequence, [])
            times.append(time.monotonic())
            if len(times) == len(header.stack.z_um):
                acknowledge({"sequence": header.stack.sequence, "last_arrival_s": times[-1]})

        def on_focus_frame(
            key: str, payload: bytes, attachment: bytes | None, arrived_s: float, cpu_s: float
        ) -> None:
            result = analyser.add(key, payload, attachment)
            if result is not None:
                acknowledge(
                    {
                        "sequence": result.sequence,
                        "latency_s": time.monotonic() - arrived_s,
                        "last_frame_cpu_s": time.thread_time() - cpu_s,
                        "best_z_um": result.best_z_um,
                        "error": result.error.message,
                    }
                )

        frames = child.declare_subscriber(
            keys.zframe_pattern(), zenoh.handlers.FifoChannel(FRAME_QUEUE)
        )
        acknowledge({"ready": True})
        for sample in frames:  # until the parent terminates this process
            arrived_s, cpu_s = time.monotonic(), time.thread_time()
            key = str(sample.key_expr)
            attachment = None if sample.attachment is None else sample.attachment.to_bytes()
            payload = codec.payload_bytes(sample.payload)
            if keys.parse_zframe_key(key).slide == FOCUS_SLIDE:
                on_focus_frame(key, payload, attachment, arrived_s, cpu_s)
            else:
                on_transport_frame(key, payload, attachment)


class Acks:
    """The child's acknowledgements, as they arrive."""

    def __init__(self) -> None:
        self._items: list[dict[str, Any]] = []
        self._arrived = threading.Condition()

    def on_sample(self, sample: zenoh.Sample) -> None:
        with self._arrived:
            self._items.append(json.loads(sample.payload.to_string()))
            self._arrived.notify_all()

    def wait(self, accept: Callable[[dict[str, Any]], bool], timeout_s: float = 120) -> dict:
        with self._arrived:
            if not self._arrived.wait_for(lambda: any(map(accept, self._items)), timeout_s):
                raise TimeoutError("no acknowledgement from the subscriber process")
            found = next(item for item in self._items if accept(item))
            self._items.remove(found)
            return found


def memcpy_s(frames: list[np.ndarray], repeats: int = 5) -> float:
    """Median seconds to copy every frame once into buffers already written once."""
    targets = [np.empty_like(frame) for frame in frames]
    for target, frame in zip(targets, frames, strict=True):  # fault the pages in first
        np.copyto(target, frame)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        for target, frame in zip(targets, frames, strict=True):
            np.copyto(target, frame)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def _random_frames(size: int, count: int) -> list[np.ndarray]:
    """`count` frames (size, size, 1) of 12-bit noise, each in a buffer of its own (as the
    instrument's, `codec.pixel_array`)."""
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(count):
        frame = codec.pixel_array((size, size, 1), np.uint16)
        frame[...] = rng.integers(0, 4096, size=frame.shape, dtype=np.uint16)
        frames.append(frame)
    return frames


def _memcpy_child(size: int, count: int, repeats: int, start: Any, done: Any) -> None:
    """The second copier of `two_copies`: copies its own stack alongside the parent's."""
    frames = _random_frames(size, count)
    start.wait()
    done.put(memcpy_s(frames, repeats))


def two_copies_s(frames: list[np.ndarray], repeats: int) -> float:
    """Median seconds per stack of `frames` while another process copies as much at the
    same time (the slower of the two)."""
    context = multiprocessing.get_context("spawn")
    start, done = context.Barrier(2), context.Queue()
    size, count = frames[0].shape[0], len(frames)
    child = context.Process(target=_memcpy_child, args=(size, count, repeats, start, done))
    child.start()
    try:
        start.wait(timeout=120)
        mine = memcpy_s(frames, repeats)
        return max(mine, done.get(timeout=120))
    finally:
        child.join()


def _stream_child(kind: str, address: str, size: int, count: int, stacks: int, done: Any) -> None:
    """Receiver of a `stream_s` run: puts None once it listens, then the monotonic time at
    which each stack's last frame was in hand."""
    if kind == "socket_tcp":
        host, port = address.rsplit(":", 1)
        with socket.create_connection((host, int(port))) as link:
            link.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)
            done.put(None)
            frame = memoryview(bytearray(size * size * 2))
            for _ in range(stacks):
                for _ in range(count):
                    received = 0
                    while received < len(frame):
                        received += link.recv_into(frame[received:])
                done.put(time.monotonic())
        return
    frame_bytes = size * size * 2
    parts_per_frame = -(-frame_bytes // codec.FRAME_PART_BYTES)
    with session.open_session(connect=[address]) as child:
        samples = child.declare_subscriber(CEILING_KEY, zenoh.handlers.FifoChannel(FRAME_QUEUE))
        done.put(None)
        pixels = np.empty(0, np.uint8)
        for index, sample in enumerate(samples, start=1):
            offset = (index - 1) % parts_per_frame * codec.FRAME_PART_BYTES
            if offset == 0:
                pixels = np.empty(frame_bytes, np.uint8)  # as `codec.FrameAssembler` does
            part = sample.payload.to_bytes()
            pixels[offset : offset + len(part)] = np.frombuffer(part, np.uint8)
            if index % (count * parts_per_frame) == 0:
                done.put(time.monotonic())
            if index == count * parts_per_frame * stacks:
                return


def stream_s(kind: str, frames: list[np.ndarray], stacks: int) -> float:
    """Median seconds per stack of `frames` sent to another process by `kind`:
    "zenoh_tcp" or "socket_tcp" (see the module's doc)."""
    context = multiprocessing.get_context("spawn")
    done = context.Queue()
    with contextlib.ExitStack() as resources:
        if kind == "socket_tcp":
            server = resources.enter_context(
                socket.create_server(("127.0.0.1", session.free_port()))
            )
            address = f"127.0.0.1:{server.getsockname()[1]}"
        else:
            address = session.loopback_endpoint()
            parent = resources.enter_context(session.open_session(listen=[address]))
        size, count = frames[0].shape[0], len(frames)
        child = context.Process(
            target=_stream_child, args=(kind, address, size, count, stacks, done)
        )
        child.start()
        resources.callback(child.join)
        if kind == "socket_tcp":
            link = resources.enter_context(server.accept()[0])
            link.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER_BYTES)
            send: Callable[[bytes | bytearray], object] = link.sendall
        else:
            put = parent.declare_publisher(
                CEILING_KEY, congestion_control=zenoh.CongestionControl.BLOCK, express=True
            ).put

            def send(frame: bytes | bytearray) -> None:
                for _, part in codec.frame_parts(frame, codec.FRAME_PART_BYTES):
                    put(part)

        done.get(timeout=120)
        time.sleep(0.5)  # a Zenoh subscription reaches the publisher
        times = []
        for _ in range(stacks):
            started_s = time.monotonic()
            for frame in frames:
                send(codec.raw_payload(frame))
            times.append(done.get(timeout=120) - started_s)
        return statistics.median(times)


def ceiling_s(kind: str, frames: list[np.ndarray], stacks: int) -> float:
    """Median seconds per stack of `frames` for the ceiling `kind` (one of CEILINGS)."""
    return two_copies_s(frames, stacks) if kind == "two_copies" else stream_s(kind, frames, stacks)


def _header(slide: str, sequence: int, frames: list[np.ndarray]) -> instrument_pb2.ZStackHeader:
    header = instrument_pb2.ZStackHeader(
        instrument="bench",
        slide=slide,
        sequence=sequence,
        z_um=list(np.arange(len(frames)) * 0.5),
        pixel_size_um=0.1,
        channel_order="L",
        bit_depth=12,
    )
    codec.describe_stack(header, (len(frames), *frames[0].shape), frames[0].dtype)
    return header


def run_path(path: str, frames: list[np.ndarray], stacks: int, fps: float) -> dict[str, list]:
    """The child's acknowledgements over `path`, by run: "transport" (`stacks` stacks as
    fast as they go; the parent's start time added as `started_s`, monotonic), then
    "focus" (`stacks` stacks paced at `fps`)."""
    endpoint = session.loopback_endpoint()
    pool_bytes = 2 * sum(frame.nbytes for frame in frames) if path == "shm" else 0
    acks = Acks()
    reports: dict[str, list] = {"transport": [], "focus": []}
    with session.open_session(listen=[endpoint], shared_memory=path == "shm") as parent:
        publisher = codec.PixelPublisher(parent, pool_bytes)
        parent.declare_subscriber(ACK_KEY, acks.on_sample)
        context = multiprocessing.get_context("spawn")
        child = context.Process(target=_child, args=(endpoint, path == "shm"))
        child.start()
        try:
            acks.wait(lambda item: item.get("ready", False))
            time.sleep(0.5)  # the child's subscription reaches this session
            for run, slide, period_s in (
                ("transport", TRANSPORT_SLIDE, 0.0),
                ("focus", FOCUS_SLIDE, 1.0 / fps),
            ):
                key = keys.zframe_key(slide, 0, 0)
                for sequence in range(stacks):
                    header = _header(slide, sequence, frames)
                    started_s = time.monotonic()
                    for index, frame in enumerate(frames):
                        while time.monotonic() < started_s + index * period_s:
                            time.sleep(0.0005)  # a camera's frame clock
                        publisher.put_frame(key, header, index, frame)
                    report = acks.wait(functools.partial(_is_of, sequence))
                    report["started_s"] = started_s
                    reports[run].append(report)
                    print(f"{path} {run} stack {sequence + 1}/{stacks}: {_line(report)}",
                          flush=True)  # fmt: skip
        finally:
            child.terminate()
            child.join()
    if path == "shm" and publisher.n_network:
        print(f"warning: {publisher.n_network} frame(s) took the network path (pool full)")
    return reports


def _is_of(sequence: int, report: dict[str, Any]) -> bool:
    return bool(report.get("sequence") == sequence)


def _line(report: dict[str, Any]) -> str:
    if "latency_s" in report:
        return f"focus result {1e3 * report['latency_s']:.1f} ms after the last frame"
    return f"{1e3 * (report['last_arrival_s'] - report['started_s']):.0f} ms"


def run(args: argparse.Namespace) -> int:
    frames = _random_frames(args.size, args.frames)
    stack_bytes = sum(frame.nbytes for frame in frames)
    copy_s = memcpy_s(frames)
    memcpy_gb_per_s = stack_bytes / copy_s / 1e9
    print(f"memcpy of a {stack_bytes / 1e6:.0f} MB stack: {1e3 * copy_s:.1f} ms "
          f"({memcpy_gb_per_s:.2f} GB/s)", flush=True)  # fmt: skip
    figures: dict[str, Any] = {
        "size": args.size,
        "frames": args.frames,
        "stack_mb": stack_bytes / 1e6,
        "memcpy_gb_per_s": memcpy_gb_per_s,
        "memcpy_frames_per_s": args.frames / copy_s,
    }
    for path in PATHS:
        reports = run_path(path, frames, args.stacks, args.fps)
        transfer_s = statistics.median(
            r["last_arrival_s"] - r["started_s"] for r in reports["transport"]
        )
        gb_per_s = stack_bytes / transfer_s / 1e9
        figures[path] = {
            "stack_ms": 1e3 * transfer_s,
            "gb_per_s": gb_per_s,
            "frames_per_s": args.frames / transfer_s,
            "memcpy_ratio": gb_per_s / memcpy_gb_per_s,
            "focus_latency_ms": 1e3 * statistics.median(r["latency_s"] for r in reports["focus"]),
            "focus_last_frame_cpu_ms": 1e3
            * statistics.median(r["last_frame_cpu_s"] for r in reports["focus"]),
        }
    figures["ceilings"] = {}
    for kind in CEILINGS:
        gb_per_s = stack_bytes / ceiling_s(kind, frames, args.stacks) / 1e9
        figures["ceilings"][kind] = {
            "gb_per_s": gb_per_s,
            "memcpy_ratio": gb_per_s / memcpy_gb_per_s,
        }
        print(f"ceiling {kind}: {gb_per_s:.2f} GB/s", flush=True)
    figures["targets"] = {
        "tcp_gb_per_s": figures["tcp"]["gb_per_s"] >= TCP_MIN_GB_PER_S,
        "tcp_memcpy_ratio": figures["tcp"]["memcpy_ratio"] >= TCP_MIN_MEMCPY_RATIO,
        "shm_memcpy_ratio": figures["shm"]["memcpy_ratio"] >= SHM_MIN_MEMCPY_RATIO,
        "focus_latency": max(figures[p]["focus_latency_ms"] for p in PATHS)
        <= 1e3 * FOCUS_MAX_LATENCY_S,
    }
    print(table(figures))
    if args.json:
        write_json(args.json, figures)
        chart(figures, args.json.with_suffix(".png"))
        print(f"wrote {args.json}, {args.json.with_suffix('.png')}")
    return 0


def chart(figures: dict[str, Any], out: Path) -> None:
    """GB/s of each path beside memcpy, the ceilings and the targets; focus latency against
    its target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (rate, latency) = plt.subplots(1, 2, figsize=(10, 4))
    names = ["memcpy", *PATHS, *CEILINGS]
    values = [
        figures["memcpy_gb_per_s"],
        *(figures[p]["gb_per_s"] for p in PATHS),
        *(figures["ceilings"][kind]["gb_per_s"] for kind in CEILINGS),
    ]
    colours = ["grey", "tab:blue", "tab:green", *["lightgrey"] * len(CEILINGS)]
    rate.bar(names, values, color=colours)
    rate.tick_params(axis="x", labelrotation=30)
    rate.axhline(TCP_MIN_GB_PER_S, color="tab:blue", ls="--", label="tcp target (GB/s)")
    rate.axhline(
        TCP_MIN_MEMCPY_RATIO * figures["memcpy_gb_per_s"],
        color="tab:blue",
        ls=":",
        label="tcp target (1/5 memcpy)",
    )
    rate.axhline(
        SHM_MIN_MEMCPY_RATIO * figures["memcpy_gb_per_s"],
        color="tab:green",
        ls=":",
        label="shm target (1/2 memcpy)",
    )
    rate.set_ylabel("GB/s")
    rate.set_title(f"{figures['frames']} frames of {figures['size']}^2 uint16, frame by frame")
    rate.legend()
    latency.bar(list(PATHS), [figures[p]["focus_latency_ms"] for p in PATHS])
    latency.axhline(1e3 * FOCUS_MAX_LATENCY_S, color="red", ls="--", label="target")
    latency.set_ylabel("ms from the last frame's arrival to the focus result")
    latency.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def table(figures: dict[str, Any]) -> str:
    """The figures as the README's table (Markdown)."""
    size, n = figures["size"], figures["frames"]
    lines = [
        f"{n} frames of {size}x{size} uint16 ({figures['stack_mb']:.0f} MB) per stack; "
        f"memcpy {figures['memcpy_gb_per_s']:.2f} GB/s",
        "",
        "| path | ms per stack | GB/s | frames/s | of memcpy | focus result after last frame |",
        "|---|---|---|---|---|---|",
    ]
    for path in PATHS:
        f = figures[path]
        lines.append(
            f"| {path} | {f['stack_ms']:.0f} | {f['gb_per_s']:.2f} | {f['frames_per_s']:.0f} | "
            f"{f['memcpy_ratio']:.2f} | {f['focus_latency_ms']:.1f} ms "
            f"({f['focus_last_frame_cpu_ms']:.1f} ms CPU) |"
        )
    lines += ["", "| ceiling, same run | GB/s | of memcpy |", "|---|---|---|"]
    for kind, ceiling in figures["ceilings"].items():
        lines.append(f"| {kind} | {ceiling['gb_per_s']:.2f} | {ceiling['memcpy_ratio']:.2f} |")
    met = ", ".join(
        f"{name} {'met' if ok else 'NOT met'}" for name, ok in figures["targets"].items()
    )
    lines += ["", f"targets: {met}"]
    return "\n".join(lines)
