"""Uploads whose headers promise far more pixels than they hold: what the REST app's limits
(`app.FocusLimits`, `focustrack_core.stacks.decode_stack`) must refuse from the header
alone, before decoding.

`focustrack bench chaos` sends them (`focustrack.bench.hostile`); the service's tests
check each refusal.
"""

from __future__ import annotations

import struct
import zlib

#: The attack's numbers: 27 frames of 8192x8192 uint16 are 3.6 GB once decoded.
BOMB_FRAMES, BOMB_SIDE = 27, 8192


def zlib_tiff_bomb(n_frames: int = BOMB_FRAMES, side: int = BOMB_SIDE) -> bytes:
    """A little-endian TIFF of `n_frames` pages of `side` x `side` uint16 zeros, zlib-compressed.

    Every page points at the same compressed strip, so the file stays near 0.1% of
    the frame's size while it decodes to n_frames * side^2 * 2 bytes.
    """
    compressor, chunk = zlib.compressobj(9), bytes(1 << 20)
    strip = b"".join(compressor.compress(chunk) for _ in range(side * side * 2 // len(chunk)))
    strip += compressor.flush()
    n_tags = 9
    ifd_size = 2 + 12 * n_tags + 4
    strip_offset = 8
    first_ifd = strip_offset + len(strip) + (len(strip) % 2)
    out = bytearray(b"II*\x00" + struct.pack("<I", first_ifd) + strip)
    out += b"\x00" * (first_ifd - len(out))
    for page in range(n_frames):
        offset = first_ifd + page * ifd_size
        next_ifd = 0 if page == n_frames - 1 else offset + ifd_size
        tags = [  # (tag, type SHORT=3 / LONG=4, value), sorted by tag
            (256, 4, side),  # ImageWidth
            (257, 4, side),  # ImageLength
            (258, 3, 16),  # BitsPerSample
            (259, 3, 8),  # Compression: Adobe deflate (zlib)
            (262, 3, 1),  # PhotometricInterpretation: black is zero
            (273, 4, strip_offset),  # StripOffsets
            (277, 3, 1),  # SamplesPerPixel
            (278, 4, side),  # RowsPerStrip
            (279, 4, len(strip)),  # StripByteCounts
        ]
        out += struct.pack("<H", len(tags))
        for tag, kind, value in tags:
            packed = struct.pack("<HH", value, 0) if kind == 3 else struct.pack("<I", value)
            out += struct.pack("<HHI", tag, kind, 1) + packed
        out += struct.pack("<I", next_ifd)
    return bytes(out)


def npy_with_shape(shape: tuple[int, ...], dtype: str = "<u2") -> bytes:
    """A .npy file whose header declares `shape` and that holds no data at all."""
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header
