"""`focustrack serve instrument`: the simulated microscope on Zenoh.

Queryables (key space in proto/README.md):
- ``focustrack/v1/instrument/{name}/acquire``: AcquireRequest in; every frame is
  published on ``focustrack/v1/zframe/{slide}/{row}/{col}`` as soon as it is rendered,
  then the whole stack on ``focustrack/v1/zstack/{slide}/{row}/{col}`` if anyone
  subscribes to it, then AcquireReply (header and timing) comes back. Bad requests
  get an Error reply; the service keeps running.
- ``focustrack/v1/instrument/{name}/info``: InstrumentInfo (slides, limits, optics).
- ``focustrack/v1/instrument/{name}/frames``: FramesRequest in; one reply per frame of
  a stack acquired lately (the frames the scheduler keeps: `recent.RecentStacks`, up to
  ``--keep-frames-mb`` of them besides the last stack), or an Error reply
  (ERROR_CODE_FRAMES_GONE when the stack is no longer held).
- ``focustrack/v1/eval/truth/{name}/{slide}``: SlideTruth, for evaluation code only, and
  only with ``--serve-truth``.

Acquisitions run one at a time on the main thread (there is one stage), which
publishes each frame while the render threads work on the next ones; info, frames and
truth are answered on Zenoh's threads. At most `--queue-depth` acquisitions wait for the
stage; one more is refused at once with ERROR_CODE_BUSY (the caller backs off and
asks again), so a burst of requests cannot make a normal one wait behind all of it.
The truth queryable is declared only with `--serve-truth` (benchmarks and tests):
the ground truth is not on the bus unless asked for. Pixels go through Zenoh shared
memory to subscribers on this host (``--shared-memory``), over the network to the others.
"""

from __future__ import annotations

import argparse
import logging
import queue
import signal
import threading
import time
from dataclasses import replace

import numpy as np
import zenoh

from focustrack_core.config import command_main
from focustrack_core.surfaces import FAMILIES, family_spec
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.session import (
    ATTEMPT_TIMEOUT_S,
    DEFAULT_ENDPOINT,
    BackgroundSession,
    add_zenoh_arguments,
    config_from_args,
    shm_pool_bytes,
)
from focustrack_instrument_sim.microscope import (
    AcquisitionRefusedError,
    Microscope,
    MicroscopeSpec,
    Refusal,
    slides_from_map,
    slides_from_seed,
)
from focustrack_instrument_sim.optics import CHANNELS, Optics
from focustrack_instrument_sim.recent import RecentStacks
from focustrack_instrument_sim.specimen import SpecimenSpec
from focustrack_instrument_sim.stage import StageSpec

log = logging.getLogger(__name__)

#: Acquisitions that may wait for the stage; one more is refused BUSY.
QUEUE_DEPTH = 4

#: Frames of past stacks kept for queries, MB, besides the last stack (`RecentStacks`):
#: two stacks of 41 frames of 1024 x 1024 RGB uint16.
KEEP_FRAMES_MB = 512

ERROR_CODES = {
    Refusal.MALFORMED: rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
    Refusal.UNKNOWN_SLIDE: rpc.ErrorCode.ERROR_CODE_UNKNOWN_SLIDE,
    Refusal.TILE_OUTSIDE_SLIDE: rpc.ErrorCode.ERROR_CODE_TILE_OUTSIDE_SLIDE,
    Refusal.Z_OUT_OF_RANGE: rpc.ErrorCode.ERROR_CODE_Z_OUT_OF_RANGE,
    Refusal.TOO_MANY_FRAMES: rpc.ErrorCode.ERROR_CODE_TOO_MANY_FRAMES,
}


class InstrumentService:
    """The Zenoh shell around a `Microscope`: declare on `start`, serve until `stop` is set."""

    def __init__(
        self,
        microscope: Microscope,
        session: zenoh.Session,
        name: str = "sim",
        *,
        realtime: bool = False,
        shm_pool_bytes: int = 0,
        frame_part_bytes: int = codec.FRAME_PART_BYTES,
        queue_depth: int = QUEUE_DEPTH,
        serve_truth: bool = False,
        keep_frames_bytes: int = KEEP_FRAMES_MB * 1_000_000,
    ) -> None:
        if queue_depth < 1:
            raise ValueError(f"queue_depth must be at least 1, got {queue_depth}")
        self.microscope = microscope
        self.session = session
        self.publisher = codec.PixelPublisher(session, shm_pool_bytes, frame_part_bytes)
        self.name = keys.check_name(name, "instrument")
        self.realtime = realtime
        self.stop = threading.Event()
        self._acquire_key = keys.acquire_key(name)
        self._pending: queue.Queue[zenoh.Query] = queue.Queue(maxsize=queue_depth)
        self.serve_truth = serve_truth
        self.n_busy = 0  # acquisitions refused because the queue was full
        self._declared: list = []
        self.recent = RecentStacks(keep_frames_bytes)

    def start(self) -> None:
        """Declare the queryables (the instrument becomes visible)."""
        info_key, frames_key = keys.info_key(self.name), keys.frames_key(self.name)
        self._declared = [
            self.session.declare_queryable(self._acquire_key, self._enqueue),
            self.session.declare_queryable(
                info_key, lambda query: rpc.answer(query, info_key, self._info)
            ),
            self.session.declare_queryable(
                frames_key, lambda query: rpc.serve(query, frames_key, self._reply_frames)
            ),
        ]
        if self.serve_truth:
            self._declared.append(
                self.session.declare_queryable(
                    keys.truth_pattern(self.name),
                    lambda query: rpc.answer(query, str(query.key_expr), self._truth),
                )
            )

    def _enqueue(self, query: zenoh.Query) -> None:
        """Queue an acquisition for the stage, or refuse it BUSY when the queue is full."""
        try:
            self._pending.put_nowait(query)
        except queue.Full:
            self.n_busy += 1
            rpc.answer(query, self._acquire_key, self._busy)

    def _busy(self, _query: zenoh.Query) -> instrument_pb2.AcquireReply:
        raise rpc.RequestError(
            rpc.ErrorCode.ERROR_CODE_BUSY,
            f"{self._pending.maxsize} acquisition(s) already wait for the stage; try again",
        )

    def serve(self) -> None:
        """Answer acquisition requests, one at a time, until `stop` is set."""
        while not self.stop.is_set():
            try:
                query = self._pending.get(timeout=0.1)
            except queue.Empty:
                continue
            rpc.answer(query, self._acquire_key, self._acquire)

    def close(self) -> None:
        for entity in self._declared:
            entity.undeclare()
        self._declared = []

    def _acquire(self, query: zenoh.Query) -> instrument_pb2.AcquireReply:
        started_s = time.perf_counter()
        request = rpc.parse_request(query, instrument_pb2.AcquireRequest)
        try:
            plan = self.microscope.plan(
                request.slide,
                request.row,
                request.col,
                request.z_low_um,
                request.z_step_um,
                request.n_frames,
                request.exposure_s or None,
            )
        except AcquisitionRefusedError as refused:
            code = ERROR_CODES[refused.reason]
            raise rpc.RequestError(code, str(refused), refused.field) from refused
        camera = self.microscope.spec.camera
        header = instrument_pb2.ZStackHeader(
            instrument=self.name,
            slide=plan.slide,
            row=plan.row,
            col=plan.col,
            sequence=request.sequence,
            stage_x_um=plan.stage_x_um,
            stage_y_um=plan.stage_y_um,
            z_um=plan.z_um.tolist(),
            pixel_size_um=self.microscope.pixel_size_um,
            channel_order=CHANNELS,
            bit_depth=camera.bit_depth,
            exposure_s=plan.exposure_s,
            clock_s=plan.clock_s,
        )
        shape = (plan.n_frames, *self.microscope.spec.shape, len(CHANNELS))
        codec.describe_stack(header, shape, np.uint16)
        frame_key = keys.zframe_key(plan.slide, plan.row, plan.col)
        stack_key = keys.zstack_key(plan.slide, plan.row, plan.col)
        # Frames in buffers of their own are sent without a copy; a stack someone wants
        # whole is rendered into one buffer instead (its frames then cost a copy each).
        stack = (
            codec.pixel_array(shape, np.uint16)
            if self.publisher.has_subscribers(stack_key)
            else None
        )
        out = stack.__getitem__ if stack is not None else self._frame_buffer
        frames = []
        for index, frame in enumerate(self.microscope.render(plan, out)):
            self.publisher.put_frame(frame_key, header, index, frame)
            frames.append(frame)
        header.timestamp_unix_s = time.time()
        self.recent.keep(header, frames, recyclable=stack is None)
        if stack is not None:
            self.publisher.put_stack(stack_key, header, stack)
        timing = plan.timing
        if self.realtime:  # pace the simulated clock: the stack takes as long as it would
            time.sleep(max(0.0, timing.total_s - (time.perf_counter() - started_s)))
        return instrument_pb2.AcquireReply(
            header=header,
            timing=instrument_pb2.Timing(
                move_s=timing.move_s,
                z_settle_s=timing.z_settle_s,
                exposure_s=timing.exposure_s,
                readout_s=timing.readout_s,
                total_s=timing.total_s,
                clock_s=plan.clock_s,
                move_distance_um=timing.move_distance_um,
            ),
        )

    def _frame_buffer(self, _index: int) -> np.ndarray:
        """A buffer to render a frame into (height, width, channels) uint16: one of a stack
        no longer kept where there is one (`RecentStacks.buffer`)."""
        return self.recent.buffer((*self.microscope.spec.shape, len(CHANNELS)), np.dtype(np.uint16))

    def _reply_frames(self, query: zenoh.Query) -> None:
        """Answer a FramesRequest with one reply per frame, as they were published."""
        request = rpc.parse_request(query, instrument_pb2.FramesRequest)
        try:
            found = self.recent.copies(
                request.slide, request.row, request.col, request.sequence, list(request.indices)
            )
        except IndexError as error:
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST, str(error), "indices"
            ) from error
        if found is None:
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_FRAMES_GONE,
                f"stack {request.sequence} of tile ({request.row}, {request.col}) of slide "
                f"{request.slide!r} is not held (any more): the instrument keeps "
                f"{self.recent.budget_bytes / 1e6:.0f} MB of past stacks besides the last",
            )
        header, frames = found
        for index, frame in frames:
            query.reply(
                query.key_expr,
                self.publisher.payload(frame),
                attachment=codec.frame_header(header, index, frame).SerializeToString(),
                encoding=codec.ZFRAME_ENCODING,
            )

    def _info(self, _query: zenoh.Query) -> instrument_pb2.InstrumentInfo:
        spec = self.microscope.spec
        optics = spec.optics
        return instrument_pb2.InstrumentInfo(
            instrument=self.name,
            slides=[
                instrument_pb2.SlideInfo(
                    slide=slide.name,
                    rows=slide.grid.rows,
                    cols=slide.grid.cols,
                    pitch_um=slide.grid.pitch_um,
                    origin_x_um=slide.grid.origin_x_um,
                    origin_y_um=slide.grid.origin_y_um,
                )
                for slide in self.microscope.slides.values()
            ],
            z_min_um=spec.stage.z_range_um[0],
            z_max_um=spec.stage.z_range_um[1],
            max_frames=spec.max_frames,
            pixel_size_um=optics.pixel_size_um,
            width=spec.width,
            height=spec.height,
            channel_order=CHANNELS,
            bit_depth=spec.camera.bit_depth,
            numerical_aperture=optics.numerical_aperture,
            magnification=optics.magnification,
            wavelength_um=optics.reference_wavelength_um,
            refractive_index=optics.refractive_index,
            depth_of_field_um=optics.depth_of_field_um,
            default_exposure_s=spec.stage.timing.exposure_s,
        )

    def _truth(self, query: zenoh.Query) -> instrument_pb2.SlideTruth:
        slide = str(query.key_expr).rsplit("/", 1)[-1]
        if slide not in self.microscope.slides:
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_UNKNOWN_SLIDE, f"unknown slide {slide!r}", "slide"
            )
        focus_um, drift_um = self.microscope.truth_um(slide)
        return instrument_pb2.SlideTruth(
            instrument=self.name,
            slide=slide,
            rows=focus_um.shape[0],
            cols=focus_um.shape[1],
            best_focus_um=focus_um.ravel().tolist(),
            drift_um=drift_um,
            clock_s=self.microscope.stage.clock_s,
        )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(parser, default_listen=[DEFAULT_ENDPOINT])
    parser.add_argument("--name", default="sim", help="instrument name in the key space")
    slides = parser.add_argument_group("slides")
    slides.add_argument("--seed", type=int, default=0, help="seed of surfaces and specimens")
    slides.add_argument("--slides", type=int, default=1, help="generated slides (slide-0, ...)")
    slides.add_argument("--rows", type=int, default=20, help="tiles per column of a slide")
    slides.add_argument("--cols", type=int, default=20, help="tiles per row of a slide")
    slides.add_argument("--family", choices=list(FAMILIES), default="standard")
    slides.add_argument("--map", help="true focus map(s) in um (.npy, .csv, .tif) to use instead")
    slides.add_argument("--pitch-um", type=float, default=200.0, help="tile centre spacing")
    slides.add_argument(
        "--z-offset-um",
        type=float,
        default=0.0,
        help="every slide's focus moved by this much (a re-scan after drift between passes)",
    )
    scope = parser.add_argument_group("microscope")
    scope.add_argument("--width", type=int, default=1024, help="frame width in pixels")
    scope.add_argument("--height", type=int, default=1024, help="frame height in pixels")
    scope.add_argument("--max-frames", type=int, default=64, help="largest z-stack accepted")
    scope.add_argument(
        "--workers", type=int, default=2, help="threads rendering the frames of a stack (2)"
    )
    scope.add_argument(
        "--cache-mb",
        type=float,
        default=1024.0,
        help="in-focus tile spectra kept, MB (1024: 244 tiles of 512 x 512, 61 of 1024 x 1024)",
    )
    scope.add_argument("--na", type=float, default=0.85, help="numerical aperture")
    scope.add_argument("--magnification", type=float, default=60.0)
    scope.add_argument("--drift-um-per-s", type=float, default=0.0, help="thermal z drift")
    scope.add_argument("--dust-density", type=float, default=0.0, help="specks per 1000 um^2")
    scope.add_argument(
        "--realtime", action="store_true", help="pace acquisitions at their simulated duration"
    )
    scope.add_argument(
        "--keep-frames-mb",
        type=float,
        default=KEEP_FRAMES_MB,
        help="frames of past stacks kept for the frames queryable, MB, besides the last "
        f"stack ({KEEP_FRAMES_MB})",
    )
    scope.add_argument(
        "--frame-part-kb",
        type=int,
        default=codec.FRAME_PART_BYTES // 1024,
        help="frames go over the network in parts of this many KiB, 0: whole "
        f"({codec.FRAME_PART_BYTES // 1024}: fastest over TCP; see proto/README.md)",
    )
    scope.add_argument(
        "--queue-depth",
        type=int,
        default=QUEUE_DEPTH,
        help=f"acquisitions that may wait for the stage; more are refused BUSY ({QUEUE_DEPTH})",
    )
    parser.add_argument(
        "--serve-truth",
        action="store_true",
        help="answer the ground truth (focustrack/v1/eval/truth/...): benchmarks and tests only",
    )


def microscope_from_args(args: argparse.Namespace) -> Microscope:
    if args.map:
        slides = slides_from_map(args.map, args.seed, args.pitch_um)
    else:
        surface = family_spec(args.family, args.rows, args.cols)
        slides = slides_from_seed(args.seed, args.slides, surface, args.pitch_um)
    if args.z_offset_um:
        slides = [replace(slide, focus_um=slide.focus_um + args.z_offset_um) for slide in slides]
    spec = MicroscopeSpec(
        optics=Optics(numerical_aperture=args.na, magnification=args.magnification),
        stage=StageSpec(drift_um_per_s=args.drift_um_per_s),
        specimen=SpecimenSpec(dust_density=args.dust_density),
        height=args.height,
        width=args.width,
        max_frames=args.max_frames,
        cache_mb=args.cache_mb,
        workers=args.workers,
    )
    return Microscope(slides, spec, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    try:
        microscope = microscope_from_args(args)
        config_from_args(args)  # a bad option or config file ends the command here, not later
        if args.queue_depth < 1:
            raise ValueError(f"--queue-depth must be at least 1, got {args.queue_depth}")
        if args.keep_frames_mb < 0:
            raise ValueError(f"--keep-frames-mb must not be negative, got {args.keep_frames_mb}")
        if args.frame_part_kb < 0:
            raise ValueError(f"--frame-part-kb must not be negative, got {args.frame_part_kb}")
    except ValueError as error:
        log.error("%s", error)
        return 2
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    # The stage waits for the bus; a router that comes later is connected to then.
    bus = BackgroundSession(lambda: config_from_args(args, ATTEMPT_TIMEOUT_S))
    try:
        session = None
        while session is None and not stop.is_set():
            session = bus.wait(1.0)
        if session is not None:
            serve(microscope, session, args, stop)
    finally:
        bus.close()
        microscope.close()
    return 0


def serve(
    microscope: Microscope, session: zenoh.Session, args: argparse.Namespace, stop: threading.Event
) -> None:
    """Run the instrument on an open session until `stop` is set."""
    service = InstrumentService(
        microscope,
        session,
        args.name,
        realtime=args.realtime,
        shm_pool_bytes=shm_pool_bytes(args),
        frame_part_bytes=args.frame_part_kb * 1024,
        queue_depth=args.queue_depth,
        serve_truth=args.serve_truth,
        keep_frames_bytes=int(args.keep_frames_mb * 1_000_000),
    )
    service.stop = stop
    service.start()
    first = next(iter(microscope.slides.values()))
    log.info(
        "instrument %r ready: %d slide(s) of %dx%d tiles, %dx%d px frames, DoF %.2f um, "
        "queue %d, truth %s",
        service.name,
        len(microscope.slides),
        first.grid.rows,
        first.grid.cols,
        microscope.spec.width,
        microscope.spec.height,
        microscope.spec.optics.depth_of_field_um,
        args.queue_depth,
        "served" if args.serve_truth else "off",
    )
    service.serve()
    service.close()


#: Every option's environment variable is this prefix and its name (focustrack_core.config).
ENV_PREFIX = "FOCUSTRACK_INSTRUMENT_"

#: The `focustrack-instrument-sim` console script (and `python -m focustrack_instrument_sim`).
main = command_main(
    "focustrack-instrument-sim", "the simulated microscope on Zenoh", add_arguments, run, ENV_PREFIX
)
