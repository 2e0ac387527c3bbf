"""How a z-stack travels: raw pixels as the payload, the ZStackHeader in the attachment.

Pixels are a C-ordered numpy array of shape (frames, height, width, channels). The
header names its dtype (with byte order) and shape, so any language can rebuild the
array without a copy of its own. Wrapping the pixels in a protobuf bytes field
(`ZStack`, kept for files) costs an extra copy at every step; proto/README.md has the
measurements behind this choice.
"""

from __future__ import annotations

import math

import numpy as np
import zenoh

from focustrack_core.v1 import instrument_pb2

#: Encoding of a z-stack sample: raw bytes, described by the attached header.
ZSTACK_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema(
    instrument_pb2.ZStackHeader.DESCRIPTOR.full_name
)


def describe_pixels(header: instrument_pb2.ZStackHeader, pixels: np.ndarray) -> None:
    """Set `header.dtype` and `header.shape` from `pixels` (frames, height, width, channels)."""
    if pixels.ndim != 4:
        raise ValueError(f"pixels must be (frames, height, width, channels), got {pixels.shape}")
    if len(header.z_um) != pixels.shape[0]:
        raise ValueError(f"header has {len(header.z_um)} z values for {pixels.shape[0]} frames")
    header.dtype = pixels.dtype.str
    del header.shape[:]
    header.shape.extend(pixels.shape)


def encode_zstack(header: instrument_pb2.ZStackHeader, pixels: np.ndarray) -> tuple[bytes, bytes]:
    """(payload, attachment) of a z-stack sample; fills in the header's dtype and shape."""
    describe_pixels(header, pixels)
    return np.ascontiguousarray(pixels).tobytes(), header.SerializeToString()


def pixels_from_bytes(header: instrument_pb2.ZStackHeader, data: bytes) -> np.ndarray:
    """The (read-only) pixel array that `header` describes, viewing `data` without a copy."""
    try:
        dtype = np.dtype(header.dtype)
    except TypeError as error:
        raise ValueError(f"z-stack header has an unknown dtype {header.dtype!r}") from error
    shape = tuple(header.shape)
    expected = math.prod(shape) * dtype.itemsize
    if len(shape) != 4 or len(data) != expected:
        raise ValueError(
            f"z-stack of shape {shape} and dtype {dtype.str} needs {expected} bytes, "
            f"got {len(data)}"
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def decode_zstack(
    payload: bytes, attachment: bytes | None
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """Header and pixels of a z-stack sample; ValueError when they do not fit together."""
    if not attachment:
        raise ValueError("z-stack sample has no header attachment")
    header = instrument_pb2.ZStackHeader.FromString(attachment)
    return header, pixels_from_bytes(header, payload)


def decode_zstack_sample(
    sample: zenoh.Sample,
) -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    """`decode_zstack` of a received Zenoh sample."""
    attachment = sample.attachment
    return decode_zstack(
        sample.payload.to_bytes(), None if attachment is None else attachment.to_bytes()
    )


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
