"""`focustrack serve focus`: the focus service on Zenoh and over REST, in one process.

Zenoh: subscribes to the frames of z-stacks, ``focustrack/v1/zframe/{slide}/...`` of every
slide or of those --slides names (one focus service per scanner), scores each
frame as it lands, and publishes a FocusResult on ``focustrack/v1/focus/{slide}/{row}/{col}``
as soon as the last frame of a stack is in (only the peak fit is left by then); a
stack that cannot be read gets a FocusResult whose `error` says why (code BAD_STACK).
Stacks taken for another purpose than focus (``ZStackHeader.purpose``: phase stacks, which
the phase service reads) are ignored.
Frames are taken from a bounded FIFO by one worker thread, so a burst waits (back
pressure to the publisher) instead of piling up without bound. What a peer's frames make
the service hold is bounded in bytes and time (`FrameAnalyser`: --open-frames-mb,
--open-frame-timeout-s), and a frame larger than its instrument's (as the instrument's
info reply describes them) is refused before anything is allocated for it. Whole-stack messages
(``focustrack/v1/zstack/...``) are for other subscribers; this service does not read them.
REST: the FastAPI app of `app.py`, served by uvicorn on --host/--port.

Every result carries the nonce of its stack's acquisition (from the frames' header), and
with ``--result-key-file`` an HMAC of it in its attachment, which the scheduler checks
(`focustrack_core.wire.trust`, docs/security.md). With ``--frame-key-file`` only frame
samples that carry the instrument's tag are scored; the others are dropped, logged and
counted (`FrameAnalyser.n_untagged`), so frames published by anyone else never become
a result. The REST API
comes up at once; the Zenoh session is opened in the background and tried again until
the router answers, so the service starts before the router (``/healthz`` says
``degraded`` until the session is open and linked).
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import fields, replace
from pathlib import Path
from typing import Annotated, ClassVar

import numpy as np
import zenoh
from google.protobuf.message import DecodeError
from opentelemetry.trace import SpanKind
from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from focustrack_core import tracing
from focustrack_core.domain import Prior
from focustrack_core.logs import worth_logging
from focustrack_core.serving import (
    ListenError,
    listening_socket,
    refuse_open_network,
    serve_until_stopped,
)
from focustrack_core.settings import command_main, one_of
from focustrack_core.tracing import TracingSettings
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2
from focustrack_core.web import with_bus_health
from focustrack_core.wire import codec, keys
from focustrack_core.wire.codec import FrameAssembler, payload_bytes, zframe_header
from focustrack_core.wire.frame_worker import FrameReaderSettings, FrameWorker, WorkerBus
from focustrack_core.wire.open_stacks import OpenStacks, stack_id
from focustrack_core.wire.rpc import protobuf_encoding
from focustrack_core.wire.session import DEFAULT_ENDPOINT
from focustrack_core.wire.trust import FrameSigner, ResultSigner
from focustrack_focus.app import LEAST_LIMITS, FocusLimits, create_app
from focustrack_focus.curve_model import CurveModel, as_modelled
from focustrack_focus.instrument_frames import InstrumentFrameSizes
from focustrack_focus.layers import learn_top
from focustrack_focus.metrics import METRICS
from focustrack_focus.peak import MAX_SYSTEMATIC_SIGMA_UM, PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusResult, FocusSettings, FrameByFrame, LastLooks
from focustrack_focus.preprocess import (
    MAX_LOWPASS_SIGMA_PX,
    Preprocess,
    lowpass_sigma_for_optics,
)
from focustrack_focus.profile import MicroscopeProfile

log = logging.getLogger(__name__)

FOCUS_RESULT_ENCODING = protobuf_encoding(focus_pb2.FocusResult)
#: What an open stack holds besides its curve and frames (its objects), bytes: counted
#: against the budget, so stacks of tiny frames cannot add up without bound either (an
#: open stack of 8 x 8 frames takes about 1.5 KB besides its arrays, by tracemalloc).
STACK_BYTES = 4096
CURVE_SLIDES = 16  # slides whose learnt focus curve is kept (the most recent)


def settings_for(
    header: instrument_pb2.ZStackHeader, base: FocusSettings, na: float | None
) -> FocusSettings:
    """`base` adapted to one stack: its green channel, and (with `na`) a low-pass matched to
    its pixel size (thesis A-1-1)."""
    preprocess = base.preprocess
    green = codec.green_channel(header)
    if green is not None:
        preprocess = replace(preprocess, channel=green)
    if na is not None and header.pixel_size_um > 0:
        sigma_px = lowpass_sigma_for_optics(header.pixel_size_um, na)
        preprocess = replace(preprocess, lowpass_sigma_px=sigma_px)
    return replace(base, preprocess=preprocess)


def prior_of(header: instrument_pb2.ZStackHeader) -> Prior | None:
    """The estimator's prediction the stack came with (None: none); ValueError for one
    `Prior` refuses (a z or sigma out of its bounds)."""
    if not (header.HasField("prior_z_um") and header.HasField("prior_sigma_um")):
        return None
    return Prior(header.prior_z_um, header.prior_sigma_um)


def result_message(
    tile: keys.TileKey,
    header: instrument_pb2.ZStackHeader | None,
    result: FocusResult | None = None,
    error: str = "",
) -> focus_pb2.FocusResult:
    """The wire FocusResult of a stack: its result, or an error saying why there is none;
    with the current span's trace context, where there is one."""
    message = focus_pb2.FocusResult(slide=tile.slide, row=tile.row, col=tile.col)
    if header is not None:
        message.sequence = header.sequence
        message.instrument = header.instrument
        message.nonce = header.nonce
    if (trace := tracing.to_wire()) is not None:  # the current span: the analysis's
        message.trace.CopyFrom(trace)
    if result is not None:
        message.metric = result.metric
        message.z_um.extend(result.z_um.tolist())
        message.scores.extend(result.scores.tolist())
        if result.best_z_um is not None:
            message.best_z_um = result.best_z_um
        if result.sigma_um is not None:
            message.sigma_um = result.sigma_um
        if result.runner_up_z_um is not None:
            message.runner_up_z_um = result.runner_up_z_um
        if result.chosen_probability is not None:
            message.chosen_probability = result.chosen_probability
        message.flags.extend(sorted(flag.proto for flag in result.flags))
        message.compute_time_s = result.compute_time_s
    if error:
        message.error.CopyFrom(
            common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK, message=error)
        )
    return message


def _place(curve: FrameByFrame, frame: instrument_pb2.ZFrameHeader) -> int:
    """Where `frame` lies in `curve`: its index in its stack, after the look joined before
    the stack's frames where there is one (`LastLooks`)."""
    return frame.index + curve.z_um.size - len(frame.stack.z_um)


def _check_same_stack(curve: FrameByFrame, frame: instrument_pb2.ZFrameHeader) -> None:
    """ValueError unless `frame`'s header gives its stack the heights the stack's first
    frame gave (the tail of `curve`'s, after a joined look): a frame saying 3 frames after
    one saying 21 was placed among the 21, and the stack never answered."""
    z_um = np.asarray(frame.stack.z_um)
    if z_um.size > curve.z_um.size or not np.array_equal(curve.z_um[-z_um.size :], z_um):
        raise ValueError(
            f"frame {frame.index}'s header gives its stack {z_um.size} frames at other "
            "heights than its first frame's"
        )


def _no_frame_size(_instrument: str) -> int | None:
    return None


class FrameAnalyser:
    """Frame samples in (whole, or in parts), a FocusResult out as soon as the last frame
    of a stack lands.

    Stacks are told apart by their key, sequence number, simulated clock and nonce (an
    acquisition taken again keeps its sequence). A frame that comes twice starts its
    stack over; one that cannot be read (or a part lost) ends its stack with an error
    result. With a `frame_signer`, a sample whose attachment does not carry that key's
    tag of it is dropped before anything else (no result, not even an error), logged and
    counted in `n_untagged`. A frame of a stack whose purpose is not focus (a phase stack,
    for the phase service) is ignored, counted in `n_not_focus`. A look (a stack of one
    frame) is held until its slide's next stack, which reads it as its first frame where it
    is the rest of the look's stack (`pipeline.LastLooks`); one that does not fit in the
    budget is not held.

    Memory is bounded in bytes and time, whatever peers send: the frames under way (in
    parts), what open stacks hold (each keeps its sharpest and blurriest frames for
    the structure test) and the held looks together stay within `budget_bytes`. A frame
    is refused, and its stack ends with an error result (counted in `n_refused`), when it
    is larger than `frame_bytes_of(instrument)` says the instrument named in its header
    takes (None: not known), before anything is allocated for it; when its buffer (a
    frame in parts) does not fit, before it is taken; and when its stack would keep more
    of it than fits, once it is scored. A stack whose next frame, or a frame whose next part, has
    not come within `timeout_s` (by `clock`, s) is dropped (`n_expired` stacks) at the
    next `add` or `expire`.
    """

    def __init__(
        self,
        base: FocusSettings,
        na: float | None,
        budget_bytes: int = codec.OPEN_FRAMES_BYTES,
        timeout_s: float = codec.OPEN_FRAME_TIMEOUT_S,
        *,
        frame_bytes_of: Callable[[str], int | None] = _no_frame_size,
        clock: Callable[[], float] = time.monotonic,
        frame_signer: FrameSigner | None = None,
    ) -> None:
        self.base = base
        self.na = na
        self.budget_bytes = budget_bytes
        self.timeout_s = timeout_s
        self.frame_bytes_of = frame_bytes_of
        self.clock = clock
        self.frame_signer = frame_signer
        self.n_untagged = 0  # frame samples dropped: their tag was missing or wrong
        self.n_not_focus = 0  # frame samples of stacks taken for another purpose (phase)
        self._refused = 0  # frames refused here (`n_refused`)
        self.n_expired = 0  # stacks dropped: their next frame did not come in time
        # curves under way (each holding `FrameByFrame.held_bytes` and STACK_BYTES)
        self._open: OpenStacks[FrameByFrame] = OpenStacks(clock)
        self._looks = LastLooks(CURVE_SLIDES)  # each slide's last look, for the stack after it
        self._frames = FrameAssembler(
            budget_bytes,
            timeout_s,
            held_elsewhere=lambda: self._open.held_bytes + self._looks.held_bytes,
            clock=clock,
        )
        # each slide's through-focus curve, learnt from its full stacks, reads its short ones
        self._curves: OrderedDict[str, CurveModel] = OrderedDict()

    @property
    def n_refused(self) -> int:
        """Frames refused: larger than their instrument's, or over the budget (each ends
        its stack)."""
        return self._refused + self._frames.n_refused

    @property
    def open_bytes(self) -> int:
        """Bytes held for stacks under way: their frames in parts, what open stacks keep,
        and the slides' last looks."""
        return self._frames.open_bytes + self._open.held_bytes + self._looks.held_bytes

    def expire(self) -> None:
        """Drop the stacks (and frames in parts) that peers stopped sending `timeout_s` ago."""
        self._frames.expire()
        for (key, sequence, _, _), curve in self._open.expired(self.timeout_s):
            self.n_expired += 1
            missing = int(np.isnan(curve.scores).sum())
            log.warning(
                "stack %d on %s dropped: %d frame(s) did not come within %g s",
                sequence,
                key,
                missing,
                self.timeout_s,
            )

    def add(
        self, key: str, payload: bytes, attachment: bytes | None
    ) -> focus_pb2.FocusResult | None:
        """The stack's FocusResult when this frame completes it (or ends it in error), else
        None. ValueError only when the key names no tile (there is nowhere to answer)."""
        tile = keys.parse_zframe_key(key)
        if self.frame_signer is not None and not self._tagged(key, payload, attachment):
            self.n_untagged += 1
            if worth_logging(self.n_untagged):  # a forger cannot flood the log
                log.warning(
                    "frame sample on %s dropped (%d so far): no tag of the instrument's frame key",
                    key,
                    self.n_untagged,
                )
            return None
        header = None
        try:
            frame_header = zframe_header(attachment)
            header = frame_header.stack
            if header.purpose != instrument_pb2.ACQUISITION_PURPOSE_FOCUS:
                self.n_not_focus += 1  # a stack for another service (phase): none of ours
                return None
            stack = stack_id(key, header)
            self.expire()
            if self._open.failed(stack):
                return None  # the stack was already answered with an error
            self._check_frame_size(header)
            frame = self._frames.add(key, frame_header, payload)
            if frame is None:
                return None  # a part of the frame: more to come
            curve = self._open.pop(stack)
            if curve is not None:
                _check_same_stack(curve, frame_header)
            if curve is not None and not np.isnan(curve.scores[_place(curve, frame_header)]):
                log.warning(
                    "frame %d on %s came again: stack started over", frame_header.index, key
                )
                curve = None
            if curve is None:  # the stack's first frame (joined to its look, where it had one)
                settings = settings_for(header, self.base, self.na)
                place = (tile.row, tile.col)
                curve = self._looks.curve(
                    tile.slide,
                    place,
                    np.asarray(header.z_um),
                    settings,
                    pairs=self._curve(tile.slide).ready,  # a pair is read with the slide's curve
                )
            curve.add(_place(curve, frame_header), frame[..., 0] if frame.shape[-1] == 1 else frame)
            if not curve.complete:
                held = STACK_BYTES + curve.held_bytes
                self._fit(held)  # what the stack keeps of this frame, besides the others
                self._open.put(stack, curve, held)
                return None
            parent = header.trace if header.HasField("trace") else None
            with tracing.joined("focus stack", parent, SpanKind.CONSUMER, sequence=header.sequence):
                model, place = self._curve(tile.slide), (tile.row, tile.col)
                beside = model.beside_layers(place)  # a fold's band: its tops read sooner
                result = curve.result(model, prior_of(header), beside_layers=beside)
                if curve.held_bytes <= self.budget_bytes - self.open_bytes:
                    self._looks.keep(tile.slide, place, curve)
                # learnt as the slide's curve reads (a valley's reciprocal: `as_modelled`)
                mode = curve.settings.peak.mode
                z_um, scores = as_modelled(result.z_um, result.scores, mode)
                flags, best_z_um = result.flags, result.best_z_um
                model.learn(z_um, scores, best_z_um, flags)
                if learn_top(
                    model.top_widths_um, z_um, scores, best_z_um, flags, beside_layers=beside
                ):
                    model.layered_tiles.add(place)
                return result_message(tile, header, result)  # with this span's context
        except Exception as error:  # a bad frame is answered with an error, never a crash
            log.warning("frame on %s: %s", key, error)
            if header is not None:
                self._open.fail(stack_id(key, header))
            return result_message(tile, header, error=f"{type(error).__name__}: {error}")

    def _check_frame_size(self, header: instrument_pb2.ZStackHeader) -> None:
        """Refuse a stack whose frames are larger than its instrument's."""
        size = codec.frame_bytes(header)
        largest = self.frame_bytes_of(header.instrument)
        if largest is not None and size > largest:
            self._refused += 1
            raise ValueError(
                f"frames of {size} bytes declared; instrument {header.instrument!r} takes "
                f"frames of {largest} bytes"
            )

    def _fit(self, held_bytes: int) -> None:
        """Refuse (ValueError) a stack that would hold more than the budget has room for."""
        room = self.budget_bytes - self.open_bytes
        if held_bytes > room:
            self._refused += 1
            raise ValueError(
                f"the stack would hold {held_bytes} bytes; {room} of the budget of "
                f"{self.budget_bytes} bytes for open frames are left"
            )

    def _tagged(self, key: str, payload: bytes, attachment: bytes | None) -> bool:
        """True when the sample's attachment is a frame header followed by the frame key's
        tag of it and of `payload`."""
        assert self.frame_signer is not None  # asked only then
        if not attachment:
            return False
        try:
            header = instrument_pb2.ZFrameHeader.FromString(attachment)
        except DecodeError:
            return False
        return self.frame_signer.verify(key, header, attachment, payload)

    def _curve(self, slide: str) -> CurveModel:
        """The slide's curve model (a new one for a new slide; the oldest beyond CURVE_SLIDES
        is forgotten)."""
        model = self._curves.pop(slide, None) or CurveModel()
        self._curves[slide] = model
        while len(self._curves) > CURVE_SLIDES:
            self._curves.popitem(last=False)
        return model


class ZenohFocusWorker:
    """Subscribes to z-stack frames and publishes their focus results, on its own thread
    (`FrameWorker`)."""

    def __init__(
        self,
        session: zenoh.Session,
        settings: FocusSettings,
        na: float | None = None,
        signer: ResultSigner | None = None,
        open_frames_bytes: int = codec.OPEN_FRAMES_BYTES,
        open_frame_timeout_s: float = codec.OPEN_FRAME_TIMEOUT_S,
        frame_signer: FrameSigner | None = None,
        slides: str = "*",
    ):
        self.session = session
        self.analyser = FrameAnalyser(
            settings,
            na,
            open_frames_bytes,
            open_frame_timeout_s,
            frame_bytes_of=InstrumentFrameSizes(session),
            frame_signer=frame_signer,
        )
        self.signer = signer
        self.n_published = 0
        self._frames = FrameWorker(
            session,
            "focus",
            lambda key, payload, attachment: self.analyser.add(
                key, payload_bytes(payload), attachment
            ),
            self._publish,
            self.analyser.expire,
            min(1.0, self.analyser.timeout_s / 4),
            keys.zframe_pattern(slides),
            keys.alive_key("focus", slides, str(session.info.zid())),
        )

    def _publish(self, message: focus_pb2.FocusResult) -> None:
        key_expr = keys.focus_key(message.slide, message.row, message.col)
        payload = message.SerializeToString()
        self.session.put(
            key_expr,
            payload,
            encoding=FOCUS_RESULT_ENCODING,
            congestion_control=zenoh.CongestionControl.BLOCK,
            attachment=None if self.signer is None else self.signer.tag(key_expr, payload),
        )
        self.n_published += 1

    def close(self, timeout_s: float = 5.0) -> None:
        self._frames.close(timeout_s)


class FocusServiceSettings(FrameReaderSettings, TracingSettings):
    """The focus service's options: flags, ``FOCUSTRACK_FOCUS_<OPTION>`` or a settings file.

    The focus maths' defaults are its own dataclasses' (`FocusSettings`, `PeakSettings`,
    `Preprocess`, and the REST app's `FocusLimits`), which lab software uses without the
    service: the options read their defaults from there, and `focus_settings` and `limits`
    give the values back as those dataclasses, which check them.
    """

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_FOCUS_")
    default_connect: ClassVar[tuple[str, ...]] = (DEFAULT_ENDPOINT,)

    host: str = Field("127.0.0.1", description="HTTP address")
    port: int = Field(8002, ge=0, le=65535, description="HTTP port")
    metric: Annotated[str, one_of(METRICS)] = Field(
        FocusSettings.metric, description="the focus metric"
    )
    focus_mode: PeakMode = Field(
        PeakSettings.mode, description="max: stained specimens; valley: unstained, phase-like ones"
    )
    lowpass_sigma_px: float | None = Field(
        None,
        le=MAX_LOWPASS_SIGMA_PX,
        description="Gaussian low-pass sigma, px (default: matched to each stack's pixel size "
        f"and --na; {Preprocess.lowpass_sigma_px:g} px where a stack gives no pixel size)",
    )
    na: float = Field(
        0.85, gt=0, le=1.7, description="numerical aperture of the objective (at most 1.7)"
    )
    slides: str = Field(
        "*",
        description="read the stacks of these slides only: a name, '*' standing for any "
        "characters (scanner-1-*: one focus service per scanner; *: every slide)",
    )
    min_structure_snr: float = Field(
        FocusSettings.min_structure_snr,
        allow_inf_nan=True,  # -inf: never flat (no other option takes infinity); NaN: refused
        description="a stack whose through-focus change stands fewer noise spreads than this "
        "above its pixel noise is flat (--min-structure-snr=-inf: never)",
    )
    # the metric's constants on this microscope (`PeakSettings`; `bench focus --real` learns
    # them from labelled curves): without them, short windows of noise can read as peaks
    # and a metric's offset from a person's focus is not in sigma
    min_relative_noise: float = Field(
        PeakSettings.min_relative_noise,
        ge=0,
        le=1,
        description="the metric's score noise as a share of a curve's maximum (1: the metric "
        "is unusable on this microscope, every result is flat)",
    )
    systematic_sigma_um: float = Field(
        PeakSettings.systematic_sigma_um,
        ge=0,
        le=MAX_SYSTEMATIC_SIGMA_UM,
        description="the metric's offset from the true focus, a std added to sigma, um "
        f"(at most {MAX_SYSTEMATIC_SIGMA_UM:g})",
    )
    profile: Path | None = Field(
        None,
        description="a microscope profile (`focustrack focus calibrate --out`): each metric's "
        "constants, picked by a curve's metric label; they replace the two options above",
    )
    token: str | None = Field(None, description="require this bearer token on /v1 (unset: no auth)")
    insecure: bool = Field(
        False,
        description="serve REST without a token on a non-loopback address (refused otherwise)",
    )
    # the REST API's limits (`FocusLimits`)
    max_upload_bytes: int = Field(
        FocusLimits.max_upload_bytes,
        ge=LEAST_LIMITS["max_upload_bytes"],
        description="largest request body, bytes (413)",
    )
    max_decoded_bytes: int = Field(
        FocusLimits.max_decoded_bytes,
        ge=LEAST_LIMITS["max_decoded_bytes"],
        description="largest decoded stack, bytes, read from its header (413)",
    )
    max_frames: int = Field(
        FocusLimits.max_frames,
        ge=LEAST_LIMITS["max_frames"],
        description="most frames of a stack or points of a curve",
    )
    max_json_bytes: int = Field(
        FocusLimits.max_json_bytes,
        ge=LEAST_LIMITS["max_json_bytes"],
        description="largest JSON body of /v1/focus/curve, bytes (413)",
    )
    max_json_depth: int = Field(
        FocusLimits.max_json_depth,
        ge=LEAST_LIMITS["max_json_depth"],
        description="deepest nesting of a JSON body (422)",
    )
    body_timeout_s: float = Field(
        FocusLimits.body_timeout_s,
        gt=0,
        description="seconds a request body may take to arrive (408)",
    )
    max_concurrent: int = Field(
        FocusLimits.max_concurrent,
        ge=LEAST_LIMITS["max_concurrent"],
        description="stacks read over REST at once; one more is answered 503 with "
        "Retry-After before its body is read (each holds up to its upload and its decoded "
        "frames: this bounds the memory)",
    )
    # what peers' frames on Zenoh may make the service hold (`FrameAnalyser`)

    @field_validator("min_structure_snr")
    @classmethod
    def _snr_not_nan(cls, snr: float) -> float:
        # `ge=-inf` refused NaN in words that did not say so ("greater than or equal to -inf")
        if math.isnan(snr):
            raise ValueError("a number of noise spreads, or -inf (never flat); got NaN")
        return snr

    @field_validator("slides")
    @classmethod
    def _slides_key_chunk(cls, slides: str) -> str:
        keys.slides_chunk(slides)  # a ValueError names what is wrong
        return slides

    def focus_settings(self) -> FocusSettings:
        """How the service reads stacks and curves (ValueError if the maths refuses a value)."""
        preprocess = (
            Preprocess()
            if self.lowpass_sigma_px is None
            else Preprocess(lowpass_sigma_px=self.lowpass_sigma_px)
        )
        peak = PeakSettings(
            mode=self.focus_mode,
            min_relative_noise=self.min_relative_noise,
            systematic_sigma_um=self.systematic_sigma_um,
        )
        return FocusSettings(preprocess, self.metric, peak, self.min_structure_snr)

    def limits(self) -> FocusLimits:
        """What one REST request may ask (the options' bounds are the limits' own)."""
        return FocusLimits(
            **{limit.name: getattr(self, limit.name) for limit in fields(FocusLimits)}
        )

    @property
    def stack_na(self) -> float | None:
        """The NA each stack's low-pass is matched to; None where --lowpass-sigma-px fixes it."""
        return self.na if self.lowpass_sigma_px is None else None


#: Seconds after start that the focus maths' scipy parts are imported in the background:
#: /healthz answers first, and the first stack does not wait the 1-1.5 s they take.
WARM_UP_DELAY_S = 0.5


def _import_the_maths_scipy() -> None:
    """What `peak` and `curve_model` import on first use (scipy.signal, special, optimize)."""
    import scipy.optimize
    import scipy.signal
    import scipy.special  # noqa: F401


def run(settings: FocusServiceSettings) -> int:
    refusal = refuse_open_network("focus", settings.host, settings.token, settings.insecure)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    try:
        limits = settings.limits()
        focus = settings.focus_settings()
        profile = MicroscopeProfile.load(settings.profile) if settings.profile else None
    except ValueError as error:
        print(f"focus service not started: {error}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        signer, frame_signer = settings.signers()
        settings.check_listen()  # a Zenoh port in use: one line, not a wait for ever
        # bound before the bus and the log say where it is: a port in use is one line
        listening = listening_socket(settings.host, settings.port, "focus")
    except (ValueError, ListenError) as error:
        log.error("%s", error)
        return 2
    tracing.configure("focustrack-focus", settings.otlp_endpoint)
    bus = WorkerBus(
        settings,
        lambda session: ZenohFocusWorker(
            session,
            profile.settings_for(focus.metric, focus) if profile else focus,
            settings.stack_na,
            signer,
            settings.open_frames_bytes,
            settings.open_frame_timeout_s,
            frame_signer,
            settings.slides,
        ),
    )
    log.info(
        "focus service: zenoh %s (%s) -> %s/focus/... (results %s), http://%s:%d (metric %s)",
        keys.zframe_pattern(settings.slides),
        "any frames" if frame_signer is None else "tagged frames only",
        keys.PREFIX,
        "tagged" if signer is not None else "untagged",
        settings.host,
        listening.getsockname()[1],  # --port 0: the one the system chose
        focus.metric,
    )
    started = time.perf_counter()
    warm_up = threading.Timer(WARM_UP_DELAY_S, _import_the_maths_scipy)
    warm_up.daemon = True
    warm_up.start()
    try:
        app = create_app(focus, limits, settings.token or None, profile)
        app = with_bus_health(app, bus.health)
        serve_until_stopped(app, listening, log_level="info")
    finally:
        bus.close()
        published = sum(worker.n_published for worker in bus.workers)
        untagged = sum(worker.analyser.n_untagged for worker in bus.workers)
        log.info(
            "published %d results in %.0f s; dropped %d untagged frame samples",
            published,
            time.perf_counter() - started,
            untagged,
        )
    return 0


#: The command's settings model (`focustrack serve focus` parses it and calls `run`).
Settings = FocusServiceSettings

#: The `focustrack-focus` console script (and `python -m focustrack_focus`).
main = command_main(
    "focustrack-focus", "the focus service (Zenoh and REST)", FocusServiceSettings, run
)
