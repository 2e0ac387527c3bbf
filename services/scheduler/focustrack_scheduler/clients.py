"""The Zenoh side of the scheduler: the instrument's queryables, the focus and phase results.

`InstrumentClient` asks the instrument (info, acquire, the frames a tile keeps, and
the evaluation-only truth); an `Inbox` takes the focus service's results as they arrive by
subscription, each only for the acquisition the engine awaits (its sequence, tile,
frames and nonce) and only once, for the engine to wait on; with phase, another takes the
phase service's results the same way (`PhaseReceived`, matched by `phase_refusal`).
The scheduler does not subscribe to the frames: only the focus service needs every one,
and the scheduler fetches the few it keeps once their tile's focus is known.
"""

from __future__ import annotations

import hmac
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
import zenoh

from focustrack_core import tracing
from focustrack_core.domain import Acquisition
from focustrack_core.geometry import ScanGrid
from focustrack_core.logs import worth_logging
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2, phase_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.session import AliveTokens
from focustrack_core.wire.trust import ResultSigner
from focustrack_scheduler.plan import AcquirePhase, SlideGeometry, StageLimits

log = logging.getLogger(__name__)


def stage_limits(info: instrument_pb2.InstrumentInfo) -> StageLimits:
    """The travel and frame limit the instrument's info states; a travel that is not a finite
    z_min_um < z_max_um, or a frame limit below 1, as not stated (an instrument older than
    them sends zeros)."""
    stated = math.isfinite(info.z_min_um) and math.isfinite(info.z_max_um)
    travel = stated and info.z_min_um < info.z_max_um
    return StageLimits(
        info.z_min_um if travel else None,
        info.z_max_um if travel else None,
        info.max_frames if info.max_frames >= 1 else None,
    )


def acquire_request(
    slide: str, acquisition: Acquisition, nonce: bytes
) -> instrument_pb2.AcquireRequest:
    """The AcquireRequest of an estimator acquisition (its index is the wire sequence),
    taken this time under `nonce` (fresh for every request: `trust.new_nonce`), with the
    estimator's prediction of the tile's focus as its prior where it has a finite one (the
    focus service weighs the stack's peaks with it)."""
    z = acquisition.z
    request = instrument_pb2.AcquireRequest(
        slide=slide,
        row=acquisition.row,
        col=acquisition.col,
        z_low_um=z.low_um,
        z_step_um=z.step_um,
        n_frames=z.n_frames,
        sequence=acquisition.index,
        nonce=nonce,
    )
    z_um, sigma_um = acquisition.predicted_um, acquisition.predicted_sigma_um
    if (
        z_um is not None
        and sigma_um is not None
        and math.isfinite(z_um + sigma_um)
        and sigma_um > 0
    ):
        request.prior_z_um, request.prior_sigma_um = z_um, sigma_um
    return request


def phase_request(step: AcquirePhase, nonce: bytes) -> instrument_pb2.AcquireRequest:
    """The AcquireRequest of a phase stack (purpose phase, its reference plane), under `nonce`."""
    return instrument_pb2.AcquireRequest(
        slide=step.slide,
        row=step.row,
        col=step.col,
        z_low_um=step.z.low_um,
        z_step_um=step.z.step_um,
        n_frames=step.z.n_frames,
        sequence=step.sequence,
        nonce=nonce,
        purpose=instrument_pb2.ACQUISITION_PURPOSE_PHASE,
        reference_z_um=step.reference_z_um,
    )


def same_stack(acquisition: Acquisition, row: int, col: int, z_um: list[float]) -> bool:
    """True when a focus result at (row, col) of frames at `z_um` is of this acquisition's
    tile and frames: those alone, or after the frame of the tile's look taken just before
    them (the focus service reads a look and the rest of its stack as one curve)."""
    looked = len(z_um) - acquisition.z.n_frames
    return (
        (row, col) == (acquisition.row, acquisition.col)
        and looked in (0, 1)
        and abs(z_um[looked] - acquisition.z.low_um) < 1e-3
    )


def refusal(
    slide: str, acquisition: Acquisition, nonce: bytes, result: focus_pb2.FocusResult
) -> str | None:
    """Why `result` is not the focus result of `acquisition` of `slide` taken under
    `nonce`, or None when it is: same slide and sequence, same nonce (compared in constant
    time), and its tile and frames (or its tile and an error: a stack the focus service
    could not read)."""
    if result.sequence != acquisition.index:
        return f"no acquisition {result.sequence} is awaited"
    if result.slide != slide:
        return f"slide {result.slide!r}, not {slide!r}"
    if not hmac.compare_digest(result.nonce, nonce):
        return "another acquisition's nonce: an old result replayed, or a stale one"
    if not (
        same_stack(acquisition, result.row, result.col, list(result.z_um))
        or (
            (result.row, result.col) == (acquisition.row, acquisition.col)
            and result.HasField("error")
        )
    ):
        return f"tile ({result.row}, {result.col}) or frames not of acquisition {acquisition.index}"
    return None


@dataclass(frozen=True)
class PhaseReceived:
    """A phase result as the scheduler takes it: its header and, unless it reports an
    error, its field, float32 (2, height, width): the phase (rad), then the amplitude."""

    result: phase_pb2.PhaseResult
    field: np.ndarray | None


#: A phase stack awaited: its step, and the nonce it was taken under.
PhaseAwaited = tuple[AcquirePhase, bytes]


def phase_refusal(awaited: PhaseAwaited, received: PhaseReceived) -> str | None:
    """Why `received` is not the result of the phase stack `awaited`, or None when it is:
    same sequence, slide, tile and nonce (compared in constant time)."""
    step, nonce = awaited
    result = received.result
    if result.sequence != step.sequence:
        return f"no phase stack {result.sequence} is awaited"
    if result.slide != step.slide or (result.row, result.col) != (step.row, step.col):
        return f"tile {result.slide}/({result.row}, {result.col}), not the stack's"
    if not hmac.compare_digest(result.nonce, nonce):
        return "another acquisition's nonce: an old result replayed, or a stale one"
    return None


class InstrumentClient:
    """Queries to one instrument; `RemoteError` when it refuses or does not answer."""

    def __init__(self, session: zenoh.Session, name: str, timeout_s: float = 30.0) -> None:
        self.session = session
        self.name = keys.check_name(name, "instrument")
        self.timeout_s = timeout_s

    def info(self, timeout_s: float | None = None) -> instrument_pb2.InstrumentInfo:
        return rpc.call(
            self.session,
            keys.info_key(self.name),
            instrument_pb2.AcquireRequest(),
            instrument_pb2.InstrumentInfo,
            timeout_s or self.timeout_s,
        )

    def geometry(self, slide: str, timeout_s: float | None = None) -> SlideGeometry:
        """The grid of `slide`, the depth of field, the stage's limits and whether the
        instrument has a laser; ValueError if the slide is unknown."""
        info = self.info(timeout_s)
        for described in info.slides:
            if described.slide == slide:
                grid = ScanGrid(
                    described.rows,
                    described.cols,
                    described.pitch_um,
                    described.origin_x_um,
                    described.origin_y_um,
                )
                laser = info.laser if info.HasField("laser") else None
                return SlideGeometry(grid, info.depth_of_field_um, stage_limits(info), laser)
        known = ", ".join(described.slide for described in info.slides) or "none"
        raise ValueError(f"instrument {self.name!r} has no slide {slide!r} (it has: {known})")

    def acquire(self, request: instrument_pb2.AcquireRequest) -> instrument_pb2.AcquireReply:
        return rpc.call(
            self.session,
            keys.acquire_key(self.name),
            request,
            instrument_pb2.AcquireReply,
            self.timeout_s,
        )

    def frames(
        self, slide: str, row: int, col: int, sequence: int, indices: list[int]
    ) -> tuple[instrument_pb2.ZStackHeader, list[np.ndarray]]:
        """The header of stack `sequence` of tile (row, col) and its frames at `indices`
        (height, width, channels), from the instrument's frames queryable.

        Raises RemoteError when the instrument refuses (ERROR_CODE_FRAMES_GONE: it no
        longer holds the stack) or does not answer with every frame.
        """
        request = instrument_pb2.FramesRequest(
            slide=slide, row=row, col=col, sequence=sequence, indices=indices
        )
        key_expr = keys.frames_key(self.name)
        header, frames = None, {}
        with tracing.query_span(key_expr) as attachment:
            replies = self.session.get(
                key_expr,
                payload=request.SerializeToString(),
                encoding=rpc.protobuf_encoding(instrument_pb2.FramesRequest),
                timeout=self.timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,  # every frame replies on one key
                attachment=attachment,
            )
            for reply in replies:
                if reply.err is not None:
                    raise rpc.RemoteError(rpc.error_of(reply.err))
                if reply.ok is None:
                    continue
                try:
                    frame_header, frame = codec.decode_zframe_sample(reply.ok)
                except ValueError as error:
                    raise rpc.RemoteError(
                        common_pb2.Error(
                            code=rpc.ErrorCode.ERROR_CODE_BAD_STACK,
                            message=f"unreadable frame from {key_expr}: {error}",
                        )
                    ) from error
                header, frames[frame_header.index] = frame_header.stack, frame
        missing = sorted(set(indices) - set(frames))
        if header is None or missing:
            raise rpc.RemoteError(
                common_pb2.Error(
                    code=rpc.ErrorCode.ERROR_CODE_UNAVAILABLE,
                    message=f"{key_expr} sent no frame {missing or indices} of stack {sequence}",
                )
            )
        return header, [frames[index] for index in indices]

    def slide_truth(self, slide: str, timeout_s: float = 5.0) -> instrument_pb2.SlideTruth:
        """The evaluation-only truth of `slide`: each tile's best focus and, for a virtual
        slide, its contents (`truth_empty`)."""
        return rpc.call(
            self.session,
            keys.truth_key(self.name, slide),
            instrument_pb2.AcquireRequest(),
            instrument_pb2.SlideTruth,
            timeout_s,
        )

    def truth_um(self, slide: str, timeout_s: float = 5.0) -> np.ndarray:
        """The true best focus (rows, cols) in um, from the evaluation-only truth queryable."""
        truth = self.slide_truth(slide, timeout_s)
        return np.array(truth.best_focus_um, dtype=float).reshape(truth.rows, truth.cols)


def truth_empty(truth: instrument_pb2.SlideTruth) -> np.ndarray | None:
    """Which tiles of a virtual slide are empty glass, (rows, cols) bool; None for a slide
    of separate fields (its truth says nothing of contents)."""
    if len(truth.empty) != truth.rows * truth.cols:
        return None
    return np.array(truth.empty, dtype=bool).reshape(truth.rows, truth.cols)


def wait_for_instrument(
    session: zenoh.Session, name: str, timeout_s: float
) -> instrument_pb2.InstrumentInfo:
    """The instrument's info once it answers; RemoteError after `timeout_s` without an answer."""
    client = InstrumentClient(session, name)
    deadline_s = time.monotonic() + timeout_s
    while True:
        try:
            return client.info(timeout_s=1.0)
        except rpc.RemoteError:
            if time.monotonic() > deadline_s:
                raise
            time.sleep(0.2)


A = TypeVar("A")
R = TypeVar("R")


#: How often `Inbox.wait` asks whether its result was lost (s).
LOST_POLL_S = 0.25


class Inbox(Generic[A, R]):
    """The results the engine awaits, each taken once; filled from a Zenoh callback
    thread, read by the engine's thread.

    The engine says which stack it is about to take (its wire sequence, and what it awaits
    of it `A`: the acquisition and its nonce) before it asks for it (`expect`); `offer`
    takes a result `R` only when `refusal(awaited, result)` finds nothing wrong and none
    was taken for that sequence yet, and says why not otherwise; `wait` hands it over and
    closes the sequence, so a later copy is refused too (`forget` closes it unread).
    """

    def __init__(
        self, refusal: Callable[[A, R], str | None], sequence_of: Callable[[R], int]
    ) -> None:
        self._refusal = refusal
        self._sequence_of = sequence_of
        self._expected: dict[int, A] = {}  # by sequence
        self._taken: dict[int, R] = {}
        self._changed = threading.Condition()

    def expect(self, sequence: int, awaited: A) -> None:
        """Await the result of stack `sequence` as `awaited` (instead of any earlier take)."""
        with self._changed:
            self._expected[sequence] = awaited
            self._taken.pop(sequence, None)

    def offer(self, result: R) -> str | None:
        """None when `result` is taken, else why it is refused (not awaited, another nonce,
        slide or tile, or a second copy)."""
        sequence = self._sequence_of(result)
        with self._changed:
            expected = self._expected.get(sequence)
            if expected is None:
                return f"no acquisition {sequence} is awaited (a copy, or a late result)"
            why = self._refusal(expected, result)
            if why is None and sequence in self._taken:
                why = f"a second result for acquisition {sequence}"
            if why is None:
                self._taken[sequence] = result
                self._changed.notify_all()
            return why

    def ready(self, sequence: int) -> bool:
        """Whether a result for stack `sequence` was taken (`wait` then hands it over at once)."""
        with self._changed:
            return sequence in self._taken

    def wait(
        self, sequence: int, timeout_s: float, lost: Callable[[], bool] = lambda: False
    ) -> R | None:
        """The result taken for stack `sequence` (awaited by `expect`), or None after
        `timeout_s` or once `lost()` says it will not come (asked every LOST_POLL_S, outside
        the lock the Zenoh callbacks take: a `session.LinkWatch`'s); either way it is
        awaited no longer."""
        deadline_s = time.monotonic() + timeout_s
        try:
            while True:
                with self._changed:
                    remaining_s = deadline_s - time.monotonic()
                    if sequence not in self._taken and remaining_s > 0:
                        self._changed.wait(min(remaining_s, LOST_POLL_S))
                    result = self._taken.get(sequence)
                if result is not None:
                    return result
                if time.monotonic() >= deadline_s or lost():
                    return None
        finally:
            self.forget(sequence)

    def forget(self, sequence: int) -> None:
        """Await stack `sequence` no longer (a result for it, taken or to come, is dropped)."""
        with self._changed:
            self._expected.pop(sequence, None)
            self._taken.pop(sequence, None)


def focus_inbox() -> Inbox[tuple[str, Acquisition, bytes], focus_pb2.FocusResult]:
    """The focus results awaited: each acquisition's (slide, acquisition, nonce)."""
    return Inbox(lambda awaited, result: refusal(*awaited, result), lambda r: r.sequence)


def phase_inbox() -> Inbox[PhaseAwaited, PhaseReceived]:
    """The phase results awaited: each phase stack's step and nonce."""
    return Inbox(phase_refusal, lambda received: received.result.sequence)


class SlideListener:
    """Subscribes to the focus results of one slide (and with `phase`, its phase results),
    and keeps the liveliness tokens of the focus services that read it (`focus_services`;
    with `phase`, of the phase services too: `phase_services`); close it when done.

    With a `trust` key, a result is read only when it carries that key's tag
    (`focustrack_core.wire.trust`: a focus result's attachment is its tag, a phase
    result's header ends with it); a result enters `focus` (or `phase`) only for the stack
    awaited, once (`Inbox.offer`). The others are dropped, logged and counted in
    `n_rejected` (focus) and `n_phase_rejected`, and `on_rejected` is called for each.
    """

    def __init__(
        self,
        session: zenoh.Session,
        slide: str,
        trust: ResultSigner | None = None,
        *,
        phase: bool = False,
        on_rejected: Callable[[], None] = lambda: None,
    ) -> None:
        self.focus = focus_inbox()
        self.phase = phase_inbox()
        self.trust = trust
        self.n_rejected = 0
        self.n_phase_rejected = 0
        self.on_rejected = on_rejected
        self._subscribers = [session.declare_subscriber(keys.focus_pattern(slide), self._on_focus)]
        try:
            if phase:
                self._subscribers.append(
                    session.declare_subscriber(keys.phase_pattern(slide), self._on_phase)
                )
            self.focus_services = AliveTokens(session, keys.alive_pattern("focus", slide))
        except BaseException:
            for subscriber in self._subscribers:
                subscriber.undeclare()
            raise
        self.phase_services: AliveTokens | None = None
        try:
            if phase:
                self.phase_services = AliveTokens(session, keys.alive_pattern("phase", slide))
        except BaseException:
            self.close()
            raise

    def _on_focus(self, sample: zenoh.Sample) -> None:
        key_expr = str(sample.key_expr)
        payload = codec.payload_bytes(sample.payload)
        if self.trust is not None:
            tag = None if sample.attachment is None else sample.attachment.to_bytes()
            if not self.trust.verify(key_expr, payload, tag):
                self._reject(
                    key_expr,
                    "no tag" if tag is None else "wrong tag: not from the trusted focus service",
                )
                return
        try:
            result = focus_pb2.FocusResult.FromString(payload)
        except Exception as error:  # a DecodeError; logged, since Zenoh would swallow it
            log.warning("unreadable focus result on %s: %s", key_expr, error)
            return
        why = self.focus.offer(result)
        if why is not None:
            self._reject(key_expr, why)

    def _on_phase(self, sample: zenoh.Sample) -> None:
        key_expr = str(sample.key_expr)
        payload = codec.payload_bytes(sample.payload)
        attachment = b"" if sample.attachment is None else sample.attachment.to_bytes()
        why: str | None
        try:
            result = phase_pb2.PhaseResult.FromString(attachment)
            if self.trust is not None and not self.trust.verify_attachment(
                key_expr, result, attachment, payload
            ):
                why = "no tag or a wrong tag: not from the trusted phase service"
            else:
                field = None if result.HasField("error") else codec.phase_field(result, payload)
                why = self.phase.offer(PhaseReceived(result, field))
        except Exception as error:  # unreadable (DecodeError, ValueError): Zenoh would swallow it
            why = f"unreadable phase result: {error}"
        if why is not None:
            self.n_phase_rejected += 1  # only Zenoh's callback thread counts
            self.on_rejected()
            if worth_logging(self.n_phase_rejected):
                log.warning(
                    "phase result on %s rejected (%d so far): %s",
                    key_expr,
                    self.n_phase_rejected,
                    why,
                )

    def _reject(self, key_expr: str, why: str) -> None:
        self.n_rejected += 1  # only Zenoh's callback thread counts
        self.on_rejected()
        if worth_logging(self.n_rejected):  # replays come by the thousand
            log.warning(
                "focus result on %s rejected (%d so far): %s", key_expr, self.n_rejected, why
            )

    def close(self) -> None:
        self.focus_services.close()
        if self.phase_services is not None:
            self.phase_services.close()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers = []
