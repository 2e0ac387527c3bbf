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
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import numpy.typing as npt
import zenoh
from zenoh import shm

from focustrack_core.v1 import instrument_pb2

log = logging.getLogger(__name__)

#: Encoding of a z-stack sample: raw bytes, described by the attached header.
ZSTACK_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.ZStackHeader.DESCRIPTOR.full_name
)
#: Encoding of a frame sample: the raw bytes of one frame, described by the attached header.
ZFRAME_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.ZFrameHeader.DESCRIPTOR.full_name
)

Payload = bytes | bytearray | zenoh.ZBytes


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


def _dtype_of(header: instrument_pb2.ZStackHeader) -> np.dtype:
    try:
        return np.dtype(header.dtype)
    except TypeError as error:
        raise ValueError(f"z-stack header has an unknown dtype {header.dtype!r}") from error


def _view(data: bytes, dtype: np.dtype, shape: tuple[int, ...], what: str) -> np.ndarray:
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


def decode_zstack(
    payload: bytes, attachment: bytes | None
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """Header and pixels of a z-stack sample; ValueError when they do not fit together."""
    if not attachment:
        raise ValueError("z-stack sample has no header attachment")
    header = instrument_pb2.ZStackHeader.FromString(attachment)
    return header, pixels_from_bytes(header, payload)


def decode_zframe(
    payload: bytes, attachment: bytes | None
) -> tuple[instrument_pb2.ZFrameHeader, np.ndarray]:
    """Header and pixels (a read-only view (h, w, channels) of `payload`) of a frame sample.

    ValueError when the header is missing or the payload does not fit it.
    """
    if not attachment:
        raise ValueError("frame sample has no header attachment")
    header = instrument_pb2.ZFrameHeader.FromString(attachment)
    stack = header.stack
    if len(stack.shape) != 4 or len(stack.z_um) != stack.shape[0]:
        raise ValueError(
            f"frame header's stack has shape {tuple(stack.shape)} and {len(stack.z_um)} z "
            "values; expected (frames, height, width, channels) and one z per frame"
        )
    if header.index >= stack.shape[0]:
        raise ValueError(f"frame {header.index} of a stack of {stack.shape[0]} frames")
    return header, _view(payload, _dtype_of(stack), tuple(stack.shape[1:]), "frame")


def payload_bytes(payload: zenoh.ZBytes) -> bytes:
    """The one copy of a received payload out of Zenoh: `bytes()` of a shared-memory one
    (8 MB in 0.53 ms against 0.77 ms by `to_bytes()`, measured here), else `to_bytes()`."""
    shared = payload.as_shm()
    return bytes(shared) if shared is not None else payload.to_bytes()


def _parts(sample: zenoh.Sample) -> tuple[bytes, bytes | None]:
    attachment = sample.attachment
    return payload_bytes(sample.payload), None if attachment is None else attachment.to_bytes()


def decode_zstack_sample(
    sample: zenoh.Sample,
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """`decode_zstack` of a received Zenoh sample."""
    return decode_zstack(*_parts(sample))


def decode_zframe_sample(
    sample: zenoh.Sample,
) -> tuple[instrument_pb2.ZFrameHeader, np.ndarray]:
    """`decode_zframe` of a received Zenoh sample."""
    return decode_zframe(*_parts(sample))


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


#: Collect chunks that subscribers have released, then give up (the network path takes over).
_SHM_POLICY = shm.GarbageCollect()


class PixelPublisher:
    """Puts pixels on Zenoh with congestion control BLOCK (Zenoh's DROP loses large samples).

    With `shm_pool_bytes` > 0, each payload is copied once into a Zenoh shared-memory
    pool of that size: a subscriber on this host with shared memory enabled maps it
    without a copy, and Zenoh sends its bytes over the network to any other. A payload
    larger than the pool, or one that finds the pool full of unreleased chunks, takes
    the network path by itself (never blocking on memory).
    """

    def __init__(self, session: zenoh.Session, shm_pool_bytes: int = 0) -> None:
        self.session = session
        self.shm_pool_bytes = shm_pool_bytes
        self._provider = shm.ShmProvider.default_backend(shm_pool_bytes) if shm_pool_bytes else None
        self.n_shared = 0  # payloads that went through shared memory
        self.n_network = 0  # payloads handed to Zenoh as bytes

    def payload(self, pixels: np.ndarray) -> Payload:
        """What to put for `pixels`: a shared-memory buffer where possible, else its bytes."""
        data = raw_payload(pixels)
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
        """Publish a whole stack on `key_expr` (fills in the header's dtype and shape)."""
        describe_pixels(header, pixels)
        self._put(key_expr, pixels, header.SerializeToString(), ZSTACK_ENCODING)

    def put_frame(
        self, key_expr: str, stack: instrument_pb2.ZStackHeader, index: int, frame: np.ndarray
    ) -> None:
        """Publish frame `index` (h, w, channels) of the stack that `stack` describes."""
        attachment = frame_header(stack, index, frame).SerializeToString()
        self._put(key_expr, frame, attachment, ZFRAME_ENCODING)

    def _put(
        self, key_expr: str, pixels: np.ndarray, attachment: bytes, encoding: zenoh.Encoding
    ) -> None:
        self.session.put(
            key_expr,
            self.payload(pixels),
            attachment=attachment,
            encoding=encoding,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,  # megabytes fill their batches anyway: 10% faster over TCP unbatched
        )
