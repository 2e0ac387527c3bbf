"""`focustrack serve instrument`: a microscope on Zenoh, the simulator by default (or a
real one through Micro-Manager, `--backend mmcore`).

A thin shell over any `instrument.Instrument` (`--backend`, `backends.BACKENDS`): it
queues acquisitions, publishes their frames and stacks, keeps the last ones' frames
for the frames queryable, and answers info and truth from the instrument.

Queryables (key space in proto/README.md):
- ``focustrack/v1/instrument/{name}/acquire``: AcquireRequest in; every frame is
  published on ``focustrack/v1/zframe/{slide}/{row}/{col}`` as soon as it is taken,
  then the whole stack on ``focustrack/v1/zstack/{slide}/{row}/{col}`` if anyone
  subscribes to it, then AcquireReply (header and timing) comes back. Bad requests
  get an Error reply (a refusal or a device's failure: `request_error`); the service
  keeps running.
- ``focustrack/v1/instrument/{name}/info``: InstrumentInfo (slides, limits, optics).
- ``focustrack/v1/instrument/{name}/frames``: FramesRequest in; one reply per frame of
  a stack acquired lately (the frames the scheduler keeps: `recent.RecentStacks`, up to
  ``--keep-frames-mb`` of them besides the last stack), or an Error reply
  (ERROR_CODE_FRAMES_GONE when the stack is no longer held).
- ``focustrack/v1/eval/truth/{name}/{slide}``: SlideTruth, for evaluation code only, and
  only with ``--serve-truth`` (an instrument that is a `TruthSource`: the simulator).
- ``focustrack/v1/eval/phase/{name}/{slide}/{row}/{col}``: a tile's true phase (raw
  float32 (height, width) radians, PhaseTruth attached), for evaluation code only, with
  ``--serve-truth`` (an instrument that is a `PhaseTruthSource`: the simulator).

Every stack header says what the stack is for (`purpose`, and the `reference_z_um` of a
phase stack, both echoed from the request) and how its frames were formed (wavelength,
condenser and objective NA, the camera's photons per count and dark counts).

Acquisitions run one at a time on the main thread (there is one stage), which
publishes each frame while the instrument takes the next ones; info, frames and truth
are answered on Zenoh's threads. At most `--queue-depth` acquisitions wait for the
stage; one more is refused at once with ERROR_CODE_BUSY (the caller backs off and
asks again), so a burst of requests cannot make a normal one wait behind all of it.
The truth queryable is declared only with `--serve-truth` (benchmarks and tests):
the ground truth is not on the bus unless asked for. Pixels go through Zenoh shared
memory to subscribers on this host (``--shared-memory``), over the network to the others.
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager

import numpy as np
import zenoh

from focustrack_core import tracing
from focustrack_core.domain import MAX_ABS_Z_UM, MAX_PRIOR_SIGMA_UM, MIN_PRIOR_SIGMA_UM
from focustrack_core.http_metrics import metrics_server
from focustrack_core.serving import ListenError
from focustrack_core.settings import command_main
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.session import ATTEMPT_TIMEOUT_S, BackgroundSession
from focustrack_core.wire.trust import MAX_NONCE_BYTES, FrameSigner, frame_signer_of, new_nonce
from focustrack_instrument_sim import laser
from focustrack_instrument_sim.backends import BACKENDS
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    DeviceError,
    DeviceTimeoutError,
    Instrument,
    InstrumentError,
    NoImageError,
    PhaseTruthSource,
    Purpose,
    Refusal,
    StackPlan,
    StackRequest,
    TargetNotReachedError,
    TruthSource,
)
from focustrack_instrument_sim.laser import LaserSensor
from focustrack_instrument_sim.metrics import InstrumentMetrics
from focustrack_instrument_sim.recent import RecentStacks, StackGoneError
from focustrack_instrument_sim.settings import (
    KEEP_FRAMES_MB,
    QUEUE_DEPTH,
    InstrumentSettings,
    InstrumentShellSettings,
)

log = logging.getLogger(__name__)

#: The error reply of each refusal.
REFUSAL_CODES = {
    Refusal.MALFORMED: rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
    Refusal.UNKNOWN_SLIDE: rpc.ErrorCode.ERROR_CODE_UNKNOWN_SLIDE,
    Refusal.TILE_OUTSIDE_SLIDE: rpc.ErrorCode.ERROR_CODE_TILE_OUTSIDE_SLIDE,
    Refusal.Z_OUT_OF_RANGE: rpc.ErrorCode.ERROR_CODE_Z_OUT_OF_RANGE,
    Refusal.TOO_MANY_FRAMES: rpc.ErrorCode.ERROR_CODE_TOO_MANY_FRAMES,
}

#: The error reply of each failure of a device, the most specific first.
DEVICE_ERROR_CODES: tuple[tuple[type[DeviceError], rpc.ErrorCode], ...] = (
    (DeviceTimeoutError, rpc.ErrorCode.ERROR_CODE_DEVICE_TIMEOUT),
    (TargetNotReachedError, rpc.ErrorCode.ERROR_CODE_TARGET_NOT_REACHED),
    (NoImageError, rpc.ErrorCode.ERROR_CODE_NO_IMAGE),
    (DeviceError, rpc.ErrorCode.ERROR_CODE_DEVICE_FAILURE),
)


def request_error(error: InstrumentError) -> rpc.RequestError:
    """The error reply of what an instrument raised: a refusal's code and field, a failed
    device's code, INTERNAL for any other InstrumentError."""
    if isinstance(error, AcquisitionRefusedError):
        return rpc.RequestError(REFUSAL_CODES[error.reason], str(error), error.field)
    code = next(
        (code for kind, code in DEVICE_ERROR_CODES if isinstance(error, kind)),
        rpc.ErrorCode.ERROR_CODE_INTERNAL,
    )
    return rpc.RequestError(code, str(error))


@contextmanager
def replies_for_instrument_errors() -> Iterator[None]:
    """Turn an InstrumentError raised within into its error reply (`request_error`)."""
    try:
        yield
    except InstrumentError as error:
        if isinstance(error, DeviceError):
            log.error("instrument failed: %s", error)
        raise request_error(error) from error


#: The wire's AcquisitionPurpose of each purpose.
PURPOSES = {
    Purpose.FOCUS: instrument_pb2.ACQUISITION_PURPOSE_FOCUS,
    Purpose.PHASE: instrument_pb2.ACQUISITION_PURPOSE_PHASE,
}

#: Encoding of a phase-truth reply: raw float32 pixels, described by the attached header.
PHASE_TRUTH_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.PhaseTruth.DESCRIPTOR.full_name
)


def purpose_of(value: int) -> Purpose:
    """The purpose of a request's AcquisitionPurpose; RequestError(MALFORMED) for a value
    this instrument does not know."""
    for purpose, wire in PURPOSES.items():
        if wire == value:
            return purpose
    raise rpc.RequestError(
        rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST, f"unknown purpose {value}", "purpose"
    )


def check_prior(request: instrument_pb2.AcquireRequest) -> None:
    """RequestError(MALFORMED) naming a prediction the stack would carry to the focus
    service that `Prior` refuses there (a NaN, a sigma of 0): the whole stack was taken,
    then answered with an error."""
    bounds = {
        "prior_z_um": (-MAX_ABS_Z_UM, MAX_ABS_Z_UM),
        "prior_sigma_um": (MIN_PRIOR_SIGMA_UM, MAX_PRIOR_SIGMA_UM),
    }
    for name, (low, high) in bounds.items():
        value = getattr(request, name)
        if request.HasField(name) and not low <= value <= high:  # NaN fails it too
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
                f"{name} must be within [{low:g}, {high:g}] um, got {value}",
                name,
            )


def truth_source(instrument: Instrument, serve_truth: bool) -> TruthSource | None:
    """The instrument, to serve its ground truth from (None without `serve_truth`);
    ValueError when it has none."""
    if not serve_truth:
        return None
    if not isinstance(instrument, TruthSource):
        raise ValueError(f"--serve-truth: {type(instrument).__name__} has no ground truth")
    return instrument


class InstrumentService:
    """The Zenoh shell around an `Instrument`: declare on `start`, serve until `stop` is set."""

    def __init__(
        self,
        instrument: Instrument,
        session: zenoh.Session,
        name: str = "sim",
        *,
        realtime: bool = False,
        shm_pool_bytes: int = 0,
        frame_part_bytes: int = codec.FRAME_PART_BYTES,
        queue_depth: int = QUEUE_DEPTH,
        serve_truth: bool = False,
        keep_frames_bytes: int = KEEP_FRAMES_MB * 1_000_000,
        frame_signer: FrameSigner | None = None,
    ) -> None:
        if queue_depth < 1:
            raise ValueError(f"queue_depth must be at least 1, got {queue_depth}")
        self.instrument = instrument
        self.truth = truth_source(instrument, serve_truth)
        self.phase_truth = (
            instrument if serve_truth and isinstance(instrument, PhaseTruthSource) else None
        )
        self.session = session
        self.publisher = codec.PixelPublisher(
            session, shm_pool_bytes, frame_part_bytes, frame_signer
        )
        self.name = keys.check_name(name, "instrument")
        self.realtime = realtime
        self.stop = threading.Event()
        self._acquire_key = keys.acquire_key(name)
        self._laser_key = keys.laser_key(name)
        self.laser: LaserSensor | None = getattr(instrument, "laser", None)
        # each query with whether the laser's queryable took it: a wildcard query reaches
        # both queryables, and its key expression alone would make it two acquisitions
        self._pending: queue.Queue[tuple[zenoh.Query, bool]] = queue.Queue(maxsize=queue_depth)
        self.metrics = InstrumentMetrics(self._pending.qsize)
        self._declared: list = []
        self.recent = RecentStacks(keep_frames_bytes)

    def start(self) -> None:
        """Declare the queryables (the instrument becomes visible)."""
        info_key, frames_key = keys.info_key(self.name), keys.frames_key(self.name)
        self._declared = [
            self.session.declare_queryable(self._acquire_key, self._enqueue),
            rpc.declare_answering(self.session, info_key, self._info),
            self.session.declare_queryable(
                frames_key, lambda query: rpc.serve(query, frames_key, self._reply_frames)
            ),
        ]
        if self.truth is not None:
            self._declared.append(
                self.session.declare_queryable(
                    keys.truth_pattern(self.name),
                    lambda query: rpc.answer(query, str(query.key_expr), self._truth),
                )
            )
        if self.laser is not None:  # its readings queue for the stage, as acquisitions do
            self._declared.append(
                self.session.declare_queryable(
                    self._laser_key, lambda query: self._enqueue(query, for_laser=True)
                )
            )
        if self.phase_truth is not None:
            self._declared.append(
                self.session.declare_queryable(
                    keys.phase_truth_pattern(self.name),
                    lambda query: rpc.serve(query, str(query.key_expr), self._reply_phase_truth),
                )
            )

    def _enqueue(self, query: zenoh.Query, for_laser: bool = False) -> None:
        """Queue an acquisition (or, `for_laser`, a laser reading) for the stage, or refuse
        it BUSY when the queue is full."""
        try:
            self._pending.put_nowait((query, for_laser))
        except queue.Full:
            self.metrics.busy.inc()
            rpc.answer(query, self._laser_key if for_laser else self._acquire_key, self._busy)

    def _busy(self, _query: zenoh.Query) -> instrument_pb2.AcquireReply:
        raise rpc.RequestError(
            rpc.ErrorCode.ERROR_CODE_BUSY,
            f"{self._pending.maxsize} acquisition(s) already wait for the stage; try again",
        )

    def serve(self) -> None:
        """Answer acquisition requests, one at a time, until `stop` is set."""
        while not self.stop.is_set():
            try:
                query, for_laser = self._pending.get(timeout=0.1)
            except queue.Empty:
                continue
            if for_laser:
                rpc.answer(query, self._laser_key, self._read_laser)
            else:
                rpc.answer(query, self._acquire_key, self.metrics.observed(self._acquire))

    def _read_laser(self, query: zenoh.Query) -> instrument_pb2.LaserReading:
        assert self.laser is not None  # declared only then
        request = rpc.parse_request(query, instrument_pb2.LaserRequest)
        with replies_for_instrument_errors():
            return laser.reply(self.name, self.laser, request)

    def close(self) -> None:
        for entity in self._declared:
            entity.undeclare()
        self._declared = []

    def _acquire(self, query: zenoh.Query) -> instrument_pb2.AcquireReply:
        started_s = time.perf_counter()
        request = rpc.parse_request(query, instrument_pb2.AcquireRequest)
        if len(request.nonce) > MAX_NONCE_BYTES:
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
                f"a nonce of {len(request.nonce)} bytes; at most {MAX_NONCE_BYTES}",
                "nonce",
            )
        purpose = purpose_of(request.purpose)
        check_prior(request)
        with replies_for_instrument_errors():
            plan = self.instrument.plan(
                StackRequest(
                    request.slide,
                    request.row,
                    request.col,
                    request.z_low_um,
                    request.z_step_um,
                    request.n_frames,
                    request.exposure_s or None,  # 0 (unset on the wire): the default
                    purpose,
                    request.reference_z_um,
                    request.stage_offset_x_um,
                    request.stage_offset_y_um,
                )
            )
            header = self._header(plan, request.sequence, request.nonce or new_nonce())
            for name in ("prior_z_um", "prior_sigma_um"):  # the prediction, for the focus service
                if request.HasField(name):
                    setattr(header, name, getattr(request, name))
            shape = (plan.n_frames, *plan.frame.shape)
            codec.describe_stack(header, shape, plan.frame.dtype)
            frame_key = keys.zframe_key(plan.slide, plan.row, plan.col)
            stack_key = keys.zstack_key(plan.slide, plan.row, plan.col)
            # Frames in buffers of their own are sent without a copy; a stack someone wants
            # whole is acquired into one buffer instead (its frames then cost a copy each).
            stack = (
                codec.pixel_array(shape, plan.frame.dtype)
                if self.publisher.has_subscribers(stack_key)
                else None
            )
            out = stack.__getitem__ if stack is not None else self._frame_buffers(plan)
            frames = []
            with closing(self.instrument.acquire(plan, out)) as taken:  # stopped on a failure
                for index, frame in enumerate(taken):
                    self.publisher.put_frame(frame_key, header, index, frame)
                    frames.append(frame)
            if len(frames) < plan.n_frames:  # a stack cut short is not a stack
                raise NoImageError("camera", f"{len(frames)} of {plan.n_frames} frames came")
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

    def _header(self, plan: StackPlan, sequence: int, nonce: bytes) -> instrument_pb2.ZStackHeader:
        """The header of the stack of `plan` (without its shape and dtype yet)."""
        imaging = plan.imaging
        return instrument_pb2.ZStackHeader(
            instrument=self.name,
            slide=plan.slide,
            row=plan.row,
            col=plan.col,
            sequence=sequence,
            nonce=nonce,
            stage_x_um=plan.stage_x_um,
            stage_y_um=plan.stage_y_um,
            z_um=plan.z_um.tolist(),
            pixel_size_um=plan.pixel_size_um,
            channel_order=plan.frame.channel_order,
            bit_depth=plan.frame.bit_depth,
            exposure_s=plan.exposure_s,
            clock_s=plan.clock_s,
            purpose=PURPOSES[plan.purpose],
            reference_z_um=plan.reference_z_um,
            wavelength_um=imaging.wavelength_um,
            condenser_na=imaging.condenser_na,
            objective_na=imaging.objective_na,
            photons_per_count=imaging.photons_per_count,
            dark_counts=imaging.dark_counts,
            trace=tracing.to_wire(),  # the acquisition's span, for the focus service's to join
        )

    def _frame_buffers(self, plan: StackPlan) -> Callable[[int], np.ndarray]:
        """Buffers to take the frames of `plan` into, (height, width, channels) each: those
        of a stack no longer kept where there are some (`RecentStacks.buffer`)."""
        return lambda _index: self.recent.buffer(plan.frame.shape, plan.frame.dtype)

    def _reply_frames(self, query: zenoh.Query) -> None:
        """Answer a FramesRequest with one reply per frame asked for (each once, however
        often it is named), as they were published: each frame is copied and sent before
        the next is read, so a request holds one frame's memory at a time."""
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
            raise self._frames_gone(request)
        header, frames = found
        try:
            for index, frame in frames:
                self.publisher.reply_frame(query, header, index, frame)
        except StackGoneError as error:
            raise self._frames_gone(request) from error

    def _frames_gone(self, request: instrument_pb2.FramesRequest) -> rpc.RequestError:
        return rpc.RequestError(
            rpc.ErrorCode.ERROR_CODE_FRAMES_GONE,
            f"stack {request.sequence} of tile ({request.row}, {request.col}) of slide "
            f"{request.slide!r} is not held (any more): the instrument keeps "
            f"{self.recent.budget_bytes / 1e6:.0f} MB of past stacks besides the last",
        )

    def _info(self, _query: zenoh.Query) -> instrument_pb2.InstrumentInfo:
        with replies_for_instrument_errors():
            description = self.instrument.describe()
        frame, optics = description.frame, description.optics
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
                for slide in description.slides
            ],
            z_min_um=description.z_range_um[0],
            z_max_um=description.z_range_um[1],
            max_frames=description.max_frames,
            pixel_size_um=optics.pixel_size_um,
            width=frame.width,
            height=frame.height,
            channel_order=frame.channel_order,
            bit_depth=frame.bit_depth,
            numerical_aperture=optics.numerical_aperture,
            magnification=optics.magnification,
            wavelength_um=optics.wavelength_um,
            refractive_index=optics.refractive_index,
            depth_of_field_um=optics.depth_of_field_um,
            default_exposure_s=description.default_exposure_s,
            hardware_sequenced=description.hardware_sequenced,
            laser=self.laser is not None,
        )

    def _truth(self, query: zenoh.Query) -> instrument_pb2.SlideTruth:
        assert self.truth is not None  # declared only then
        slide = str(query.key_expr).rsplit("/", 1)[-1]
        with replies_for_instrument_errors():
            truth = self.truth.truth(slide)
        rows, cols = truth.best_focus_um.shape
        message = instrument_pb2.SlideTruth(
            instrument=self.name,
            slide=slide,
            rows=rows,
            cols=cols,
            best_focus_um=truth.best_focus_um.ravel().tolist(),
            drift_um=truth.drift_um,
            clock_s=truth.clock_s,
            lateral_offset_x_um=truth.lateral_offset_um[0],
            lateral_offset_y_um=truth.lateral_offset_um[1],
        )
        if (tiles := truth.tiles) is not None:  # a virtual slide: what lies in each tile
            message.tissue_share.extend(tiles.tissue_share.ravel().tolist())
            message.empty.extend(tiles.empty.ravel().tolist())
            message.dust_z_um.extend(tiles.dust_z_um.ravel().tolist())
            message.fold_z_um.extend(tiles.fold_z_um.ravel().tolist())
        return message

    def _reply_phase_truth(self, query: zenoh.Query) -> None:
        """Answer with the true phase of the tile the key names: its raw float32 pixels
        (height, width), radians, with a PhaseTruth header attached."""
        assert self.phase_truth is not None  # declared only then
        key_expr = str(query.key_expr)
        slide, row, col = key_expr.split("/")[-3:]
        if not (row.isdigit() and col.isdigit()):
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_MALFORMED_REQUEST,
                f"{key_expr!r}: row and col must be non-negative integers",
                "row",
            )
        with replies_for_instrument_errors():
            truth = self.phase_truth.phase_truth(slide, int(row), int(col))
        phase_rad = np.ascontiguousarray(truth.phase_rad, dtype="<f4")
        header = instrument_pb2.PhaseTruth(
            instrument=self.name,
            slide=slide,
            row=int(row),
            col=int(col),
            shape=phase_rad.shape,
            dtype=phase_rad.dtype.str,
            pixel_size_um=truth.pixel_size_um,
            focus_z_um=truth.focus_z_um,
        )
        query.reply(
            key_expr,
            phase_rad.tobytes(),
            attachment=header.SerializeToString(),
            encoding=PHASE_TRUTH_ENCODING,
        )


def open_instrument(settings: InstrumentSettings) -> Instrument:
    """The instrument of `--backend` and its options; ValueError for a bad option (then
    nothing is left open), InstrumentError when its devices fail."""
    instrument = BACKENDS[settings.backend].open(settings)
    try:
        truth_source(instrument, settings.serve_truth)
    except ValueError:
        instrument.close()
        raise
    return instrument


def run(settings: InstrumentSettings) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    try:
        settings.zenoh()  # a bad option or config file ends the command here, not later
        settings.check_listen()  # so does a Zenoh port in use, not a wait for ever
        frame_signer = frame_signer_of(settings.frame_key_file)
        instrument = open_instrument(settings)
    except (ValueError, ListenError) as error:
        log.error("%s", error)
        return 2
    except InstrumentError as error:
        log.error("the instrument did not open: %s", error)
        return 1
    tracing.configure("focustrack-instrument", settings.otlp_endpoint)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    # The stage waits for the bus; a router that comes later is connected to then.
    bus = BackgroundSession(lambda: settings.zenoh(ATTEMPT_TIMEOUT_S))
    try:
        session = None
        while session is None and not stop.is_set():
            session = bus.wait(1.0)
        if session is not None:
            serve(instrument, session, settings, stop, frame_signer)
    except ListenError as error:  # --metrics-port in use
        log.error("%s", error)
        return 2
    finally:
        bus.close()
        instrument.close()
    return 0


def serve(
    instrument: Instrument,
    session: zenoh.Session,
    settings: InstrumentShellSettings,
    stop: threading.Event,
    frame_signer: FrameSigner | None = None,
) -> None:
    """Run the instrument on an open session until `stop` is set (tagging its frames with
    `frame_signer`, the key of `settings.frame_key_file`, where there is one)."""
    service = InstrumentService(
        instrument,
        session,
        settings.name,
        realtime=settings.realtime,
        shm_pool_bytes=settings.shared_memory_bytes,
        frame_part_bytes=settings.frame_part_kb * 1024,
        queue_depth=settings.queue_depth,
        serve_truth=settings.serve_truth,
        keep_frames_bytes=int(settings.keep_frames_mb * 1_000_000),
        frame_signer=frame_signer,
    )
    service.stop = stop
    # The metrics' port first: one in use ends the command before the instrument is seen.
    with metrics_server(service.metrics.registry, settings.metrics_host, settings.metrics_port):
        service.start()
        description = instrument.describe()
        first = description.slides[0]
        log.info(
            "instrument %r ready: %d slide(s) of %dx%d tiles, %dx%d px frames, DoF %.2f um, "
            "queue %d, truth %s, frames %s",
            service.name,
            len(description.slides),
            first.grid.rows,
            first.grid.cols,
            description.frame.width,
            description.frame.height,
            description.optics.depth_of_field_um,
            settings.queue_depth,
            "served" if settings.serve_truth else "off",
            "untagged" if frame_signer is None else "tagged",
        )
        service.serve()
    service.close()


#: The service's settings model (the `focustrack` command runs `run` with it).
Settings = InstrumentSettings

#: The `focustrack-instrument-sim` console script (and `python -m focustrack_instrument_sim`).
main = command_main(
    "focustrack-instrument-sim", "the simulated microscope on Zenoh", InstrumentSettings, run
)
