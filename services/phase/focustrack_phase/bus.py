"""The phase service on Zenoh: the frames of phase stacks in, a PhaseResult per tile out.

The instrument publishes every frame of every stack on ``focustrack/v1/zframe/...`` (the
focus service reads them there too); a stack whose header's `purpose` is
``ACQUISITION_PURPOSE_PHASE`` is one for this service. Subscribing to the frames rather than
to whole stacks (``zstack``) keeps the pixels travelling once: the instrument publishes
whole stacks only while someone subscribes to them, and the scheduler gets the
reconstruction, not the stack.

`PhaseStacks` joins the frames of phase stacks (whole, or in parts) into one channel's
counts, bounded in bytes and time as the focus service's frames are; `phase_input` turns a
stack and its header into what the filter takes; `result_sample` is the PhaseResult and its
pixels; `ZenohPhaseWorker` is the shell: one thread takes the frames from a bounded FIFO
(back pressure to the publisher while a stack is reconstructed), reconstructs each stack
when its last frame is in, and publishes the result on ``focustrack/v1/phase/{slide}/{row}/{col}``.
While it reads frames it holds the liveliness token ``focustrack/v1/alive/phase/*/{zid}``:
a scan that sees it go knows the results it had yet to publish will not come.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import zenoh
from google.protobuf.message import DecodeError

from focustrack_core.logs import worth_logging
from focustrack_core.v1 import common_pb2, instrument_pb2, phase_pb2
from focustrack_core.wire import codec, keys
from focustrack_core.wire.codec import FrameAssembler, check_frame_header, payload_bytes
from focustrack_core.wire.frame_worker import FrameWorker
from focustrack_core.wire.open_stacks import OpenStacks, stack_id
from focustrack_core.wire.trust import FrameSigner, ResultSigner
from focustrack_phase.acekf import MAX_WAVELENGTH_UM, AcekfOptions, FieldEstimate, reconstruct
from focustrack_phase.app import PhaseLimits

log = logging.getLogger(__name__)

PHASE = instrument_pb2.ACQUISITION_PURPOSE_PHASE


@dataclass(frozen=True)
class PhaseOptics:
    """What the service assumes where a stack's header leaves it out (0: unknown).

    wavelength_um: the illumination's wavelength, um, for a header whose `wavelength_um`
        is 0 (an instrument that predates the field).
    """

    wavelength_um: float = 0.55

    def __post_init__(self) -> None:
        if not 0 < self.wavelength_um <= MAX_WAVELENGTH_UM:
            raise ValueError(
                f"the wavelength must be in (0, {MAX_WAVELENGTH_UM:g}] um, "
                f"got {self.wavelength_um} um"
            )


@dataclass(frozen=True)
class PhaseInput:
    """A phase stack as the filter takes it (`acekf.reconstruct`).

    counts: float32 (frames, height, width), above the camera's offset (counts - dark).
    z_um: (frames,) each frame's height from the plane to reconstruct (header z -
        reference_z_um), um.
    """

    counts: np.ndarray
    z_um: np.ndarray
    wavelength_um: float
    pixel_um: float
    photons_per_count: float
    options: AcekfOptions


def phase_input(
    header: instrument_pb2.ZStackHeader,
    counts: np.ndarray,
    optics: PhaseOptics,
    options: AcekfOptions,
) -> PhaseInput:
    """What the filter reads of a stack of raw `counts` (frames, height, width) and its
    header: the counts above the camera's offset (`dark_counts`) with the camera's gain
    (`photons_per_count`, 0: 1), the heights from `reference_z_um`, the header's
    wavelength (0: `optics`'), and `options` with the header's condenser NA (its partial
    coherence; 0, not stated: `options`' own). ValueError where the header gives no pixel
    size."""
    if not header.pixel_size_um > 0:
        raise ValueError(f"the stack's header gives no pixel size ({header.pixel_size_um} um)")
    if not header.condenser_na >= 0:  # NaN or negative: REST refuses them too
        raise ValueError(
            f"the stack's header gives a condenser NA of {header.condenser_na} (0: not stated)"
        )
    if header.condenser_na > 0:
        options = replace(options, condenser_na=header.condenser_na)
    return PhaseInput(
        counts=counts - np.float32(header.dark_counts),
        z_um=np.asarray(header.z_um, dtype=np.float64) - header.reference_z_um,
        wavelength_um=header.wavelength_um or optics.wavelength_um,
        pixel_um=header.pixel_size_um,
        photons_per_count=header.photons_per_count or 1.0,
        options=options,
    )


def result_message(
    header: instrument_pb2.ZStackHeader,
    tile: keys.TileKey,
    shape: tuple[int, int] | None = None,
    error: str = "",
) -> phase_pb2.PhaseResult:
    """The PhaseResult of a stack of `header` on `tile`: of pixels (2, *shape), or an error."""
    message = phase_pb2.PhaseResult(
        instrument=header.instrument,
        slide=tile.slide,
        row=tile.row,
        col=tile.col,
        sequence=header.sequence,
        nonce=header.nonce,
        reference_z_um=header.reference_z_um,
        pixel_size_um=header.pixel_size_um,
        stage_x_um=header.stage_x_um,
        stage_y_um=header.stage_y_um,
    )
    if shape is not None:
        message.shape.extend((2, *shape))
        message.dtype = codec.PHASE_DTYPE
    if error:
        message.error.CopyFrom(
            common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK, message=error)
        )
    return message


def result_pixels(estimate: FieldEstimate) -> bytes:
    """A result's payload: float32 (2, height, width), the phase (rad) then the amplitude."""
    field = np.stack([estimate.phase_rad, estimate.amplitude])
    return field.astype(codec.PHASE_DTYPE).tobytes()


@dataclass
class PhaseStack:
    """A whole phase stack: its header, its tile and one channel's raw counts."""

    tile: keys.TileKey
    header: instrument_pb2.ZStackHeader
    counts: np.ndarray  # float32 (frames, height, width)


@dataclass
class _StackUnderWay:
    counts: np.ndarray  # float32 (frames, height, width), filled as frames come
    received: np.ndarray  # bool (frames,)


def one_channel(header: instrument_pb2.ZStackHeader, frame: np.ndarray) -> np.ndarray:
    """The channel the service reads of a frame (height, width, channels): the only one, or
    the green one (`codec.green_channel`); ValueError for colour frames without green."""
    if frame.shape[-1] == 1:
        return frame[..., 0]
    green = codec.green_channel(header)
    if green is None or green >= frame.shape[-1]:
        raise ValueError(
            f"frames of {frame.shape[-1]} channels ordered {header.channel_order!r}: no green "
            "channel to read"
        )
    return frame[..., green]


class PhaseStacks:
    """Frame samples in (whole or in parts), whole phase stacks out, one channel each.

    Only frames of stacks whose purpose is phase are read (the others are counted in
    `n_not_phase`, their pixels never copied). With a `frame_signer`, a sample that does not
    carry the instrument's tag is dropped (counted in `n_untagged`). Stacks are told apart
    as the focus service tells them (key, sequence, simulated clock, nonce). Memory is
    bounded: a stack must be within `limits` (frames, pixels of a frame), and the stacks
    and frames under way within `budget_bytes`; a stack whose next frame has not come
    within `timeout_s` is dropped (`n_expired`). A stack that breaks a bound or whose frame
    cannot be read ends in a `StackError`, once (its later frames are ignored).
    """

    def __init__(
        self,
        limits: PhaseLimits,
        budget_bytes: int = codec.OPEN_FRAMES_BYTES,
        timeout_s: float = codec.OPEN_FRAME_TIMEOUT_S,
        *,
        frame_signer: FrameSigner | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.limits = limits
        self.budget_bytes = budget_bytes
        self.timeout_s = timeout_s
        self.frame_signer = frame_signer
        self.clock = clock
        self.n_untagged = 0
        self.n_not_phase = 0
        self.n_expired = 0
        self._open: OpenStacks[_StackUnderWay] = OpenStacks(clock)
        self._frames = FrameAssembler(
            budget_bytes, timeout_s, held_elsewhere=lambda: self._open.held_bytes, clock=clock
        )

    @property
    def open_bytes(self) -> int:
        """Bytes held for stacks under way and their frames in parts."""
        return self._frames.open_bytes + self._open.held_bytes

    def expire(self) -> None:
        """Drop the stacks (and frames in parts) whose next part stopped coming `timeout_s` ago."""
        self._frames.expire()
        for (key, sequence, _, _), _ in self._open.expired(self.timeout_s):
            self.n_expired += 1
            log.warning("phase stack %d on %s dropped: frames stopped coming", sequence, key)

    def add(
        self, key: str, payload: Callable[[], bytes], attachment: bytes | None
    ) -> PhaseStack | phase_pb2.PhaseResult | None:
        """The stack this sample completes, a PhaseResult with the error that ends its stack,
        or None (more to come, or not a sample of a phase stack). `payload` gives the
        sample's bytes (called only for a phase stack's). ValueError only when the key
        names no tile (there is nowhere to answer)."""
        tile = keys.parse_zframe_key(key)
        try:
            frame_header = instrument_pb2.ZFrameHeader.FromString(attachment or b"")
        except DecodeError:
            return None  # no stack header: no purpose, nothing of ours (and no one to answer)
        header = frame_header.stack
        if header.purpose != PHASE:
            self.n_not_phase += 1
            return None
        data = payload()
        if self.frame_signer is not None and not self.frame_signer.verify(
            key, frame_header, attachment or b"", data
        ):
            self.n_untagged += 1
            if worth_logging(self.n_untagged):
                log.warning(
                    "frame sample on %s dropped (%d so far): no tag of the instrument's frame key",
                    key,
                    self.n_untagged,
                )
            return None
        stack = stack_id(key, header)
        try:
            self.expire()
            if self._open.failed(stack):  # answered once: its later frames too are ignored
                return None
            check_frame_header(frame_header)  # a phase stack's: answered from here on
            under_way = self._open.pop(stack) or self._start(header)
            self._open.put(stack, under_way, under_way.counts.nbytes)  # counted meanwhile
            frame = self._frames.add(key, frame_header, data)
            if frame is None:
                return None  # a part of the frame: more to come
            under_way.counts[frame_header.index] = one_channel(header, frame)
            under_way.received[frame_header.index] = True
            if not under_way.received.all():
                return None
            self._open.pop(stack)
            return PhaseStack(tile, header, under_way.counts)
        except Exception as error:  # a bad frame or stack: answered, never a crash
            log.warning("phase stack on %s: %s", key, error)
            self._open.fail(stack)
            return result_message(header, tile, error=f"{type(error).__name__}: {error}")

    def _start(self, header: instrument_pb2.ZStackHeader) -> _StackUnderWay:
        """A new stack under way, once it is within the limits and the budget (ValueError)."""
        frames, height, width, _ = header.shape
        if frames < 2:
            raise ValueError(f"a phase stack needs at least 2 frames, got {frames}")
        if frames > self.limits.max_frames:
            raise ValueError(f"a stack of {frames} frames; the limit is {self.limits.max_frames}")
        if height * width > self.limits.max_pixels:
            raise ValueError(
                f"frames of {height}x{width} pixels; the limit is {self.limits.max_pixels}"
            )
        size = frames * height * width * 4
        room = self.budget_bytes - self.open_bytes
        if size > room:
            raise ValueError(
                f"the stack would hold {size} bytes; {room} of the budget of "
                f"{self.budget_bytes} bytes for open stacks are left"
            )
        return _StackUnderWay(np.zeros((frames, height, width), np.float32), np.zeros(frames, bool))


def reconstruct_stack(
    stack: PhaseStack, optics: PhaseOptics, options: AcekfOptions, fft_workers: int = 1
) -> tuple[phase_pb2.PhaseResult, bytes]:
    """The PhaseResult of a whole stack and its payload (the field's pixels); an error
    result (naming the exception) and no pixels where the filter refuses the stack or fails.
    `fft_workers`: the threads of each of the filter's FFTs."""
    started_s = time.perf_counter()
    try:
        given = phase_input(stack.header, stack.counts, optics, options)
        estimate = reconstruct(
            given.counts,
            given.z_um,
            wavelength_um=given.wavelength_um,
            pixel_um=given.pixel_um,
            photons_per_count=given.photons_per_count,
            options=given.options,
            workers=fft_workers,
        )
    except Exception as error:  # refused by the filter (ValueError) or not: answered, never a crash
        log.warning("phase stack %d of %s: %s", stack.header.sequence, stack.tile, error)
        why = f"{type(error).__name__}: {error}"
        return result_message(stack.header, stack.tile, error=why), b""
    payload = result_pixels(estimate)
    message = result_message(stack.header, stack.tile, shape=stack.counts.shape[1:])
    message.background_share = estimate.background_share or 0.0
    message.compute_time_s = time.perf_counter() - started_s
    return message, payload


class ZenohPhaseWorker:
    """Subscribes to the frames of stacks and publishes a PhaseResult for each phase stack,
    on its own thread (`FrameWorker`; module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        stacks: PhaseStacks,
        optics: PhaseOptics | None = None,
        options: AcekfOptions | None = None,
        signer: ResultSigner | None = None,
        fft_workers: int = 1,
    ) -> None:
        self.session = session
        self.stacks = stacks
        self.optics = optics or PhaseOptics()
        self.options = options or AcekfOptions()
        self.signer = signer
        self.fft_workers = fft_workers
        self.n_published = 0
        self._frames: FrameWorker[PhaseStack | phase_pb2.PhaseResult] = FrameWorker(
            session,
            "phase",
            lambda key, payload, attachment: stacks.add(
                key, partial(payload_bytes, payload), attachment
            ),
            self._answer,
            stacks.expire,
            min(1.0, stacks.timeout_s / 4),
            alive_key=keys.alive_key("phase", "*", str(session.info.zid())),
        )

    def _answer(self, done: PhaseStack | phase_pb2.PhaseResult) -> None:
        """Reconstruct a whole stack and publish its result, or publish an error result."""
        if isinstance(done, PhaseStack):
            self.publish(*reconstruct_stack(done, self.optics, self.options, self.fft_workers))
        else:
            self.publish(done, b"")

    def publish(self, message: phase_pb2.PhaseResult, payload: bytes) -> None:
        """Put a result on its tile's key: `payload` (the field's pixels, or empty for an
        error), the PhaseResult attached, tagged with the result key where there is one."""
        key_expr = keys.phase_key(message.slide, message.row, message.col)
        attachment = (
            message.SerializeToString()
            if self.signer is None
            else self.signer.attachment(key_expr, message, payload)
        )
        self.session.put(
            key_expr,
            payload,
            attachment=attachment,
            encoding=codec.PHASE_ENCODING,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self.n_published += 1

    def close(self, timeout_s: float = 5.0) -> None:
        self._frames.close(timeout_s)
