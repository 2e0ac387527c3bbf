"""How z-stacks and their frames travel: raw pixels as the payload, a protobuf header attached.

Pixels are a C-ordered numpy array: a stack of shape (frames, height, width, channels),
a frame of shape (height, width, channels). The header names the dtype (with byte
order) and the stack's shape, so any language can rebuild the array without a copy
of its own. Wrapping the pixels in a protobuf bytes field (`ZStack`, kept for files)
costs an extra copy at every step; proto/README.md has the measurements behind this.

Copies, with eclipse-zenoh 1.10 (its abi3 wheel has no buffer protocol: `ZBytes`
takes only bytes, bytearray, str or a shared-memory buffer, and gives bytes back):
- Sending: an array made by `pixel_array` lives in a bytearray of its own, which is
  handed to Zenoh as it is (no `tobytes`); Zenoh copies it once into its message, or,
  with a `PixelPublisher` that has a shared-memory pool, once into shared memory, which
  a subscriber on the same host maps without any further copy.
- Receiving: one copy out of Zenoh (`payload_bytes`: `bytes()` of a shared-memory
  payload, a third faster than `ZBytes.to_bytes()`, which the network path takes); the
  pixels are a read-only numpy view of those bytes (`pixels_from_bytes`), never copied
  again.
- Over the network a frame goes in parts of `FRAME_PART_BYTES` (`PixelPublisher`), each
  copied once more on each side: into the part, and (`FrameAssembler`) into the frame as
  it comes. That is faster all the same: a part stays in the CPU's cache through every
  copy on its way.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import zenoh
from zenoh import shm

from focustrack_core.v1 import instrument_pb2, phase_pb2
from focustrack_core.wire.trust import FrameSigner, TaggedHeader

log = logging.getLogger(__name__)

#: Encoding of a z-stack sample: raw bytes, described by the attached header.
ZSTACK_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.ZStackHeader.DESCRIPTOR.full_name
)
#: Encoding of a frame sample: the raw bytes of one frame, described by the attached header.
ZFRAME_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.ZFrameHeader.DESCRIPTOR.full_name
)

#: Encoding of a phase result sample: raw float32 pixels, described by the attached
#: PhaseResult (`phase_field`).
PHASE_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    phase_pb2.PhaseResult.DESCRIPTOR.full_name
)
#: dtype of a phase result's pixels (float32, little-endian), as `PhaseResult.dtype` names it.
PHASE_DTYPE = "<f4"

Payload = bytes | bytearray | zenoh.ZBytes

#: Bytes of each part of a frame that `PixelPublisher` sends over the network. Zenoh cuts
#: every message into batches of 64 KiB anyway; a part of 1 MiB stays in the CPU's cache
#: through each copy on its way (into the part, into Zenoh's batches, out of Zenoh), where
#: a whole 8 MB frame goes through main memory at each. Bare sessions in two processes
#: (zenoh 1.10, 2048x2048 uint16 frames, TCP loopback, 2 cores) ran at 1.9-2.1 GB/s in
#: parts of 256 KiB to 1 MiB, 1.4-1.6 GB/s with whole frames.
FRAME_PART_BYTES = 1 << 20

#: Bytes of open frames a `FrameAssembler` holds at most, by default (the focus service's
#: --open-frames-mb): thirty 8 MB frames (2048 x 2048 uint16) under way at once.
OPEN_FRAMES_BYTES = 256_000_000

#: Seconds an open frame waits for its next part before it is dropped, by default (the
#: focus service's --open-frame-timeout-s): a frame's parts follow each other within
#: milliseconds, so a frame still open after this will not be finished.
OPEN_FRAME_TIMEOUT_S = 10.0


def pixel_array(shape: tuple[int, ...], dtype: npt.DTypeLike) -> np.ndarray:
    """An uninitialised C-ordered array of `shape` over a bytearray of its own.

    Zenoh takes that bytearray as the payload (`raw_payload`), so an image rendered
    into this array is published without a copy in Python.
    """
    dtype = np.dtype(dtype)
    return np.frombuffer(bytearray(math.prod(shape) * dtype.itemsize), dtype).reshape(shape)


def _own_bytearray(pixels: np.ndarray) -> bytearray | None:
    """The bytearray `pixels` covers exactly, in C order (as `pixel_array` makes), or None."""
    if not pixels.flags.c_contiguous:
        return None
    base: object = pixels
    while isinstance(base, np.ndarray):
        base = base.base
    owner = base.obj if isinstance(base, memoryview) else base
    if not isinstance(owner, bytearray) or len(owner) != pixels.nbytes:
        return None
    start = np.frombuffer(owner, dtype=np.uint8).ctypes.data if owner else 0
    return owner if start == pixels.ctypes.data else None


def raw_payload(pixels: np.ndarray) -> bytes | bytearray:
    """The bytes Zenoh sends for `pixels`: the array's own bytearray when it has one
    (`pixel_array`: no copy), one C-ordered copy of any other array."""
    owner = _own_bytearray(pixels)
    return owner if owner is not None else np.ascontiguousarray(pixels).tobytes()


def describe_stack(
    header: instrument_pb2.ZStackHeader, shape: tuple[int, ...], dtype: npt.DTypeLike
) -> None:
    """Set `header.dtype` and `header.shape` for a stack of `shape` (frames, h, w, channels)."""
    if len(shape) != 4:
        raise ValueError(f"pixels must be (frames, height, width, channels), got {shape}")
    if len(header.z_um) != shape[0]:
        raise ValueError(f"header has {len(header.z_um)} z values for {shape[0]} frames")
    header.dtype = np.dtype(dtype).str
    del header.shape[:]
    header.shape.extend(shape)


def describe_pixels(header: instrument_pb2.ZStackHeader, pixels: np.ndarray) -> None:
    """Set `header.dtype` and `header.shape` from `pixels` (frames, height, width, channels)."""
    describe_stack(header, pixels.shape, pixels.dtype)


def encode_zstack(
    header: instrument_pb2.ZStackHeader, pixels: np.ndarray
) -> tuple[bytes | bytearray, bytes]:
    """(payload, attachment) of a z-stack sample; fills in the header's dtype and shape."""
    describe_pixels(header, pixels)
    return raw_payload(pixels), header.SerializeToString()


def frame_header(
    stack: instrument_pb2.ZStackHeader, index: int, frame: np.ndarray
) -> instrument_pb2.ZFrameHeader:
    """The header of frame `index` of a stack described by `stack` (see `describe_stack`)."""
    if len(stack.shape) != 4 or stack.dtype == "":
        raise ValueError("the stack header has no shape and dtype yet: call describe_stack")
    if not 0 <= index < stack.shape[0]:
        raise ValueError(f"frame {index} of a stack of {stack.shape[0]} frames")
    if frame.shape != tuple(stack.shape[1:]) or frame.dtype.str != stack.dtype:
        raise ValueError(
            f"frame of shape {frame.shape} and dtype {frame.dtype.str} in a stack of "
            f"{tuple(stack.shape[1:])} {stack.dtype} frames"
        )
    return instrument_pb2.ZFrameHeader(stack=stack, index=index, timestamp_unix_s=time.time())


def green_channel(header: instrument_pb2.ZStackHeader) -> int | None:
    """The index of the green channel of the stack's frames, where its channel order names
    one (a stained specimen's contrast is in green: the channel the focus and phase
    services read); None where it names none."""
    order = header.channel_order.upper()
    return order.index("G") if "G" in order else None


def _dtype_of(header: instrument_pb2.ZStackHeader) -> np.dtype:
    """The stack's pixel dtype: ValueError unless numpy knows it and it is one number (a
    structured "u2,u2" passed, and failed later where only a ValueError was expected)."""
    try:
        dtype = np.dtype(header.dtype)
    except TypeError as error:
        raise ValueError(f"z-stack header has an unknown dtype {header.dtype!r}") from error
    if dtype.fields is not None or dtype.subdtype is not None:
        raise ValueError(f"z-stack header's dtype {header.dtype!r} is not one number per pixel")
    return dtype


def _view(
    data: bytes | np.ndarray, dtype: np.dtype, shape: tuple[int, ...], what: str
) -> np.ndarray:
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise ValueError(
            f"{what} of shape {shape} and dtype {dtype.str} needs {expected} bytes, got {len(data)}"
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def pixels_from_bytes(header: instrument_pb2.ZStackHeader, data: bytes) -> np.ndarray:
    """The (read-only) pixel array that `header` describes, viewing `data` without a copy."""
    dtype, shape = _dtype_of(header), tuple(header.shape)
    if len(shape) != 4:
        raise ValueError(f"z-stack header has shape {shape}; expected 4 dimensions")
    return _view(data, dtype, shape, "z-stack")


def phase_field(result: phase_pb2.PhaseResult, payload: bytes) -> np.ndarray:
    """The (read-only) float32 (2, height, width) array of a phase result's payload, viewed
    without a copy: the phase (rad), then the amplitude. ValueError where the result does
    not describe such an array or the payload does not fit it."""
    shape = tuple(result.shape)
    if len(shape) != 3 or shape[0] != 2 or result.dtype != PHASE_DTYPE:
        raise ValueError(
            f"a phase result holds (2, height, width) {PHASE_DTYPE}, not {shape} {result.dtype!r}"
        )
    return _view(payload, np.dtype(PHASE_DTYPE), shape, "phase result")


def decode_zstack(
    payload: bytes, attachment: bytes | None
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """Header and pixels of a z-stack sample; ValueError when they do not fit together."""
    if not attachment:
        raise ValueError("z-stack sample has no header attachment")
    header = instrument_pb2.ZStackHeader.FromString(attachment)
    return header, pixels_from_bytes(header, payload)


def zframe_header(attachment: bytes | None) -> instrument_pb2.ZFrameHeader:
    """The frame header of a sample's attachment; ValueError when it is missing or does
    not describe a frame of its stack (`check_frame_header`)."""
    if not attachment:
        raise ValueError("frame sample has no header attachment")
    header = instrument_pb2.ZFrameHeader.FromString(attachment)
    check_frame_header(header)
    return header


def check_frame_header(header: instrument_pb2.ZFrameHeader) -> None:
    """ValueError unless `header` describes a frame of its stack: a 4-D shape (frames,
    height, width, channels), one z per frame, an index among the frames."""
    stack = header.stack
    if len(stack.shape) != 4 or len(stack.z_um) != stack.shape[0]:
        raise ValueError(
            f"frame header's stack has shape {tuple(stack.shape)} and {len(stack.z_um)} z "
            "values; expected (frames, height, width, channels) and one z per frame"
        )
    if header.index >= stack.shape[0]:
        raise ValueError(f"frame {header.index} of a stack of {stack.shape[0]} frames")


def _frame_view(header: instrument_pb2.ZFrameHeader, data: bytes | np.ndarray) -> np.ndarray:
    return _view(data, _dtype_of(header.stack), tuple(header.stack.shape[1:]), "frame")


def _whole_frame(header: instrument_pb2.ZFrameHeader, payload: bytes) -> np.ndarray:
    if header.parts > 1 or header.part_offset:
        raise ValueError(
            f"part at byte {header.part_offset} of a frame in {header.parts}, not a whole frame"
        )
    return _frame_view(header, payload)


def decode_zframe(
    payload: bytes, attachment: bytes | None
) -> tuple[instrument_pb2.ZFrameHeader, np.ndarray]:
    """Header and pixels (a read-only view (h, w, channels) of `payload`) of a sample that
    holds a whole frame (a frame in parts: `FrameAssembler`).

    ValueError when the header is missing or the payload does not fit it.
    """
    header = zframe_header(attachment)
    return header, _whole_frame(header, payload)


def payload_bytes(payload: zenoh.ZBytes) -> bytes:
    """The one copy of a received payload out of Zenoh: `bytes()` of a shared-memory one
    (8 MB in 0.53 ms against 0.77 ms by `to_bytes()`, measured here), else `to_bytes()`."""
    shared = payload.as_shm()
    return bytes(shared) if shared is not None else payload.to_bytes()


def _payload_and_attachment(sample: zenoh.Sample) -> tuple[bytes, bytes | None]:
    attachment = sample.attachment
    return payload_bytes(sample.payload), None if attachment is None else attachment.to_bytes()


def decode_zstack_sample(
    sample: zenoh.Sample,
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """`decode_zstack` of a received Zenoh sample."""
    return decode_zstack(*_payload_and_attachment(sample))


def decode_zframe_sample(
    sample: zenoh.Sample,
) -> tuple[instrument_pb2.ZFrameHeader, np.ndarray]:
    """`decode_zframe` of a received Zenoh sample."""
    return decode_zframe(*_payload_and_attachment(sample))


#: A frame under way in a `FrameAssembler`: its key, stack sequence, stack clock and index.
FrameId = tuple[str, int, float, int]


@dataclass
class _FrameUnderWay:
    pixels: np.ndarray  # the frame's bytes (uint8), filled up to `received`
    last_s: float  # when its last part came, by the assembler's clock, s
    received: int = 0
    parts: int = 0


def frame_bytes(stack: instrument_pb2.ZStackHeader) -> int:
    """Bytes of one frame of the stack `stack` describes (its shape and dtype); ValueError
    for an unknown dtype."""
    return math.prod(stack.shape[1:]) * _dtype_of(stack).itemsize


class FrameAssembler:
    """Frame samples in (whole, or in parts as `PixelPublisher` sends them), whole frames out.

    The parts of a frame come in order on one key; each is copied into the frame as it
    comes (so its bytes are freed at once: keeping the parts to join them at the end
    halved the rate over TCP), and the frame is whole with its last part.

    Memory is bounded in bytes, whatever a peer declares or sends: a frame's buffer is
    taken when its first part comes, only if the whole frame fits in `budget_bytes`
    beside the open frames and what `held_elsewhere()` reports (bytes its owner holds
    from earlier frames, on the same budget); otherwise the frame is refused (ValueError,
    counted in `n_refused`), and so are its later parts. A frame whose next part has not
    come within `timeout_s` (by `clock`, s) is dropped (counted in `n_expired`) at the next
    `add` or `expire`.
    """

    def __init__(
        self,
        budget_bytes: int = OPEN_FRAMES_BYTES,
        timeout_s: float = OPEN_FRAME_TIMEOUT_S,
        *,
        held_elsewhere: Callable[[], int] = lambda: 0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if budget_bytes < 0 or not timeout_s > 0:
            raise ValueError(
                f"a budget of {budget_bytes} bytes and a timeout of {timeout_s} s: the budget "
                "must not be negative and the timeout must be positive"
            )
        self.budget_bytes = budget_bytes
        self.timeout_s = timeout_s
        self.held_elsewhere = held_elsewhere
        self.clock = clock
        self.n_refused = 0  # frames refused: over the budget
        self.n_expired = 0  # frames dropped: their next part did not come in time
        self._open: OrderedDict[FrameId, _FrameUnderWay] = OrderedDict()  # oldest part first
        self._open_bytes = 0

    @property
    def open_bytes(self) -> int:
        """Bytes taken by the frames under way (their whole buffers, received or not)."""
        return self._open_bytes

    def expire(self) -> int:
        """Drop the frames whose last part came more than `timeout_s` ago; how many."""
        deadline_s = self.clock() - self.timeout_s
        expired = 0
        while self._open:
            frame_id, oldest = next(iter(self._open.items()))
            if oldest.last_s >= deadline_s:
                break
            self._drop(frame_id)
            key, sequence, _, index = frame_id
            log.warning(
                "frame %d of stack %d on %s dropped: %d part(s) came, then none for %g s",
                index,
                sequence,
                key,
                oldest.parts,
                self.timeout_s,
            )
            expired += 1
        self.n_expired += expired
        return expired

    def add(
        self, key: str, header: instrument_pb2.ZFrameHeader, payload: bytes
    ) -> np.ndarray | None:
        """The pixels (a read-only array (h, w, channels)) of the frame that this sample
        (on `key`, its attachment read by `zframe_header`) completes, else None.

        ValueError when the sample does not fit its frame, or its frame does not fit in
        the budget; the frame's parts that came before it are dropped. A first part (or a
        whole frame) starts its frame over.
        """
        self.expire()
        stack = header.stack
        frame_id = (key, stack.sequence, stack.clock_s, header.index)
        frame = self._drop(frame_id)
        if frame is not None and header.part_offset == 0:
            log.warning("frame %d on %s started over before its last part", header.index, key)
            frame = None
        if header.parts <= 1:
            return _whole_frame(header, payload)
        size = frame_bytes(stack)
        if frame is None and header.part_offset == 0:
            room = self.budget_bytes - self._open_bytes - self.held_elsewhere()
            if size > room:
                self.n_refused += 1
                raise ValueError(
                    f"a frame of {size} bytes does not fit in the {room} bytes left of the "
                    f"budget of {self.budget_bytes} bytes for open frames"
                )
            frame = _FrameUnderWay(np.empty(size, np.uint8), self.clock())  # pages taken as written
        received = 0 if frame is None else frame.received
        if frame is None or header.part_offset != received:
            raise ValueError(
                f"part of frame {header.index} at byte {header.part_offset}, expected "
                f"{received}: a part was lost or came twice"
            )
        end, parts = received + len(payload), frame.parts + 1
        if end > size or (parts == header.parts) != (end == size):
            raise ValueError(
                f"part {parts} of {header.parts} of frame {header.index} ends at byte "
                f"{end} of {size}"
            )
        frame.pixels[received:end] = np.frombuffer(payload, np.uint8)
        if parts == header.parts:
            pixels = _frame_view(header, frame.pixels)
            pixels.flags.writeable = False  # as a whole frame's view of its payload
            return pixels
        frame.received, frame.parts, frame.last_s = end, parts, self.clock()
        self._open[frame_id] = frame
        self._open_bytes += size
        return None

    def _drop(self, frame_id: FrameId) -> _FrameUnderWay | None:
        """Take the frame `frame_id` out of the open ones (its bytes off the count)."""
        frame = self._open.pop(frame_id, None)
        if frame is not None:
            self._open_bytes -= frame.pixels.nbytes
        return frame

    def add_sample(
        self, sample: zenoh.Sample
    ) -> tuple[instrument_pb2.ZFrameHeader, np.ndarray] | None:
        """Header and pixels of the frame that a received Zenoh sample completes, else None
        (ValueError as `add`, or when its attachment is no frame header)."""
        payload, attachment = _payload_and_attachment(sample)
        header = zframe_header(attachment)
        pixels = self.add(str(sample.key_expr), header, payload)
        return None if pixels is None else (header, pixels)


def encode_zstack_message(header: instrument_pb2.ZStackHeader, pixels: np.ndarray) -> bytes:
    """The self-contained `ZStack` message (pixels in a bytes field), for files."""
    describe_pixels(header, pixels)
    return instrument_pb2.ZStack(
        header=header, pixels=np.ascontiguousarray(pixels).tobytes()
    ).SerializeToString()


def decode_zstack_message(data: bytes) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """Header and pixels of a serialised `ZStack` message."""
    message = instrument_pb2.ZStack.FromString(data)
    return message.header, pixels_from_bytes(message.header, message.pixels)


def frame_parts(
    data: bytes | bytearray, part_bytes: int
) -> Iterator[tuple[int, bytes | bytearray]]:
    """(offset, payload) of each part of `data`, `part_bytes` long but the last.

    The parts of full length are one bytearray, filled anew for each: put each on Zenoh
    (which copies a bytearray before `put` returns) before drawing the next.
    """
    pixels = memoryview(data)
    part = bytearray(part_bytes)
    for offset in range(0, len(pixels), part_bytes):
        piece = pixels[offset : offset + part_bytes]
        if len(piece) < part_bytes:
            yield offset, bytes(piece)  # the last part, shorter
        else:
            part[:] = piece
            yield offset, part


#: Collect chunks that subscribers have released, then give up (the network path takes over).
_SHM_POLICY = shm.GarbageCollect()


class PixelPublisher:
    """Puts pixels on Zenoh with congestion control BLOCK (Zenoh's DROP loses large samples).

    With `shm_pool_bytes` > 0, each payload is copied once into a Zenoh shared-memory
    pool of that size: a subscriber on this host with shared memory enabled maps it
    without a copy, and Zenoh sends its bytes over the network to any other. A payload
    larger than the pool, or one that finds the pool full of unreleased chunks, takes
    the network path by itself (never blocking on memory). On the network path a frame
    goes in parts of `part_bytes` (`FRAME_PART_BYTES`; 0: whole), which a subscriber
    joins with a `FrameAssembler`. With a `signer` (the instrument's frame key) every
    sample's header is followed by its tag (`FrameSigner.attachment`).
    """

    def __init__(
        self,
        session: zenoh.Session,
        shm_pool_bytes: int = 0,
        part_bytes: int = FRAME_PART_BYTES,
        signer: FrameSigner | None = None,
    ) -> None:
        if part_bytes < 0:
            raise ValueError(f"frame parts of {part_bytes} bytes; 0 sends frames whole")
        self.session = session
        self.shm_pool_bytes = shm_pool_bytes
        self.part_bytes = part_bytes
        self.signer = signer
        self._provider = shm.ShmProvider.default_backend(shm_pool_bytes) if shm_pool_bytes else None
        self.n_shared = 0  # payloads that went through shared memory
        self.n_network = 0  # payloads handed to Zenoh as bytes (a frame in parts counts once)

    def payload(self, pixels: np.ndarray) -> Payload:
        """What to put for `pixels`: a shared-memory buffer where possible, else its bytes."""
        return self._payload(raw_payload(pixels))

    def _payload(self, data: bytes | bytearray) -> Payload:
        if self._provider is not None and len(data) <= self.shm_pool_bytes:
            try:
                chunk = self._provider.alloc(len(data), _SHM_POLICY)
            except zenoh.ZError:
                log.debug("shared-memory pool full: %d bytes take the network path", len(data))
            else:
                chunk[:] = data
                self.n_shared += 1
                return zenoh.ZBytes(chunk)
        self.n_network += 1
        return data

    def attachment(self, key_expr: str, header: TaggedHeader, data: bytes | bytearray) -> bytes:
        """The attachment of a sample of bytes `data` on `key_expr`: `header`, tagged when
        this publisher has a signer."""
        if self.signer is None:
            return header.SerializeToString()
        return self.signer.attachment(key_expr, header, data)

    def has_subscribers(self, key_expr: str) -> bool:
        """True when some subscriber matches `key_expr` (so a message there is not wasted)."""
        publisher = self.session.declare_publisher(key_expr)
        try:
            # zenoh 1.10's stubs say bool, but it is a MatchingStatus, always truthy itself
            status = publisher.matching_status
            return bool(status.matching)  # type: ignore[attr-defined]
        finally:
            publisher.undeclare()

    def put_stack(
        self, key_expr: str, header: instrument_pb2.ZStackHeader, pixels: np.ndarray
    ) -> None:
        """Publish a whole stack on `key_expr`, in one sample (fills in the header's dtype
        and shape)."""
        describe_pixels(header, pixels)
        data = raw_payload(pixels)
        attachment = self.attachment(key_expr, header, data)
        self._put(key_expr, self._payload(data), attachment, ZSTACK_ENCODING)

    def put_frame(
        self, key_expr: str, stack: instrument_pb2.ZStackHeader, index: int, frame: np.ndarray
    ) -> None:
        """Publish frame `index` (h, w, channels) of the stack that `stack` describes: whole
        through shared memory, else in parts of `part_bytes`."""
        header = frame_header(stack, index, frame)
        data = raw_payload(frame)
        payload = self._payload(data)
        if isinstance(payload, zenoh.ZBytes) or not 0 < self.part_bytes < len(data):
            attachment = self.attachment(key_expr, header, data)
            self._put(key_expr, payload, attachment, ZFRAME_ENCODING)
            return
        header.parts = -(-len(data) // self.part_bytes)
        for offset, part in frame_parts(data, self.part_bytes):
            header.part_offset = offset
            self._put(key_expr, part, self.attachment(key_expr, header, part), ZFRAME_ENCODING)

    def reply_frame(
        self, query: zenoh.Query, stack: instrument_pb2.ZStackHeader, index: int, frame: np.ndarray
    ) -> None:
        """Answer `query` with frame `index` of the stack that `stack` describes, whole, as
        `put_frame` publishes it (on the query's key)."""
        key_expr = str(query.key_expr)
        data = raw_payload(frame)
        attachment = self.attachment(key_expr, frame_header(stack, index, frame), data)
        query.reply(key_expr, self._payload(data), attachment=attachment, encoding=ZFRAME_ENCODING)

    def _put(
        self, key_expr: str, payload: Payload, attachment: bytes, encoding: zenoh.Encoding
    ) -> None:
        self.session.put(
            key_expr,
            payload,
            attachment=attachment,
            encoding=encoding,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,  # megabytes fill their batches anyway: 10% faster over TCP unbatched
        )
