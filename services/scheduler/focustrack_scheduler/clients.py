"""The Zenoh side of the scheduler: the instrument's queryables and the focus results.

`InstrumentClient` asks the instrument (info, acquire, the frames a tile keeps, and
the evaluation-only truth); `Inbox` takes the focus service's results as they arrive by
subscription, each only for the acquisition the engine awaits (its sequence, tile,
frames and nonce) and only once, for the engine to wait on. The scheduler does not
subscribe to the frames: only the focus service needs every one, and the scheduler
fetches the few it keeps once their tile's focus is known.
"""

from __future__ import annotations

import hmac
import logging
import threading
import time

import numpy as np
import zenoh

from focustrack_core.domain import Acquisition
from focustrack_core.geometry import ScanGrid
from focustrack_core.logs import worth_logging
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.trust import ResultSigner
from focustrack_scheduler.plan import SlideGeometry

log = logging.getLogger(__name__)


def acquire_request(
    slide: str, acquisition: Acquisition, nonce: bytes
) -> instrument_pb2.AcquireRequest:
    """The AcquireRequest of an estimator acquisition (its index is the wire sequence),
    taken this time under `nonce` (fresh for every request: `trust.new_nonce`)."""
    z = acquisition.z
    return instrument_pb2.AcquireRequest(
        slide=slide,
        row=acquisition.row,
        col=acquisition.col,
        z_low_um=z.low_um,
        z_step_um=z.step_um,
        n_frames=z.n_frames,
        sequence=acquisition.index,
        nonce=nonce,
    )


def same_stack(acquisition: Acquisition, row: int, col: int, z_um: list[float]) -> bool:
    """True when a focus result at (row, col) of frames at `z_um` is of this acquisition's
    tile and frames."""
    return (
        (row, col) == (acquisition.row, acquisition.col)
        and len(z_um) == acquisition.z.n_frames
        and abs(z_um[0] - acquisition.z.low_um) < 1e-3
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
        """The grid of `slide` and the depth of field; ValueError if the slide is unknown."""
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
                return SlideGeometry(grid, info.depth_of_field_um)
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
        replies = self.session.get(
            key_expr,
            payload=request.SerializeToString(),
            encoding=rpc.protobuf_encoding(instrument_pb2.FramesRequest),
            timeout=self.timeout_s,
            consolidation=zenoh.ConsolidationMode.NONE,  # every frame replies on the same key
        )
        header, frames = None, {}
        for reply in replies:
            if reply.err is not None:
                raise rpc.RemoteError(rpc.error_of(reply.err))
            if reply.ok is not None:
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

    def truth_um(self, slide: str, timeout_s: float = 5.0) -> np.ndarray:
        """The true best focus (rows, cols) in um, from the evaluation-only truth queryable."""
        truth = rpc.call(
            self.session,
            keys.truth_key(self.name, slide),
            instrument_pb2.AcquireRequest(),
            instrument_pb2.SlideTruth,
            timeout_s,
        )
        return np.array(truth.best_focus_um, dtype=float).reshape(truth.rows, truth.cols)


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


class Inbox:
    """The focus results the engine awaits, each taken once; filled from a Zenoh callback
    thread, read by the engine's thread.

    The engine says which acquisition it is about to take, and under which nonce
    (`expect`), before it asks for it; `offer` takes a result only when it is that
    acquisition's (`refusal`) and none was taken for it yet, and says why not otherwise;
    `wait` hands it over and closes the acquisition, so a later copy is refused too.
    """

    def __init__(self) -> None:
        self._expected: dict[int, tuple[str, Acquisition, bytes]] = {}  # by sequence
        self._taken: dict[int, focus_pb2.FocusResult] = {}
        self._changed = threading.Condition()

    def expect(self, slide: str, acquisition: Acquisition, nonce: bytes) -> None:
        """Await the result of `acquisition` of `slide` taken under `nonce` (instead of any
        earlier take of it)."""
        with self._changed:
            self._expected[acquisition.index] = (slide, acquisition, nonce)
            self._taken.pop(acquisition.index, None)

    def offer(self, result: focus_pb2.FocusResult) -> str | None:
        """None when `result` is taken, else why it is refused (not awaited, another nonce,
        slide or tile, or a second copy)."""
        with self._changed:
            expected = self._expected.get(result.sequence)
            if expected is None:
                return f"no acquisition {result.sequence} is awaited (a copy, or a late result)"
            why = refusal(*expected, result)
            if why is None and result.sequence in self._taken:
                why = f"a second result for acquisition {result.sequence}"
            if why is None:
                self._taken[result.sequence] = result
                self._changed.notify_all()
            return why

    def wait(self, acquisition: Acquisition, timeout_s: float) -> focus_pb2.FocusResult | None:
        """The result taken for `acquisition` (awaited by `expect`), or None after
        `timeout_s`; either way it is awaited no longer."""
        deadline_s = time.monotonic() + timeout_s
        with self._changed:
            try:
                while (result := self._taken.get(acquisition.index)) is None:
                    remaining_s = deadline_s - time.monotonic()
                    if remaining_s <= 0:
                        return None
                    self._changed.wait(remaining_s)
                return result
            finally:
                self._expected.pop(acquisition.index, None)
                self._taken.pop(acquisition.index, None)


class SlideListener:
    """Subscribes to the focus results of one slide; close it when done.

    With a `trust` key, a focus result is read only when its attachment is that key's tag
    of it (`focustrack_core.wire.trust`); a result enters `focus` only for the
    acquisition awaited, once (`Inbox.offer`). The others are dropped, logged and counted
    in `n_rejected`.
    """

    def __init__(
        self, session: zenoh.Session, slide: str, trust: ResultSigner | None = None
    ) -> None:
        self.focus = Inbox()
        self.trust = trust
        self.n_rejected = 0
        self._subscribers = [session.declare_subscriber(keys.focus_pattern(slide), self._on_focus)]

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

    def _reject(self, key_expr: str, why: str) -> None:
        self.n_rejected += 1  # only Zenoh's callback thread counts
        if worth_logging(self.n_rejected):  # replays come by the thousand
            log.warning(
                "focus result on %s rejected (%d so far): %s", key_expr, self.n_rejected, why
            )

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers = []
