"""Z-stacks uploaded to a REST service: a .npy or multi-page TIFF file, and its heights.

The focus and phase services take the same uploads, so they read them here, with the same
limits and the same errors: `UnsupportedFileError` (HTTP 415) for a file that is neither,
`TooLargeError` (413) for one that would decode to more than the limits allow, checked
from the file's header before its pixels are decoded (a 3.5 MB zlib TIFF can hold
3.6 GB), and ValueError (422) for the rest. TIFF files need tifffile (in the services'
``service`` extras), imported on the first TIFF, not at start-up.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np

_NPY_MAGIC = b"\x93NUMPY"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


class UnsupportedFileError(ValueError):
    """The upload is neither a TIFF nor a .npy file (HTTP 415)."""


class TooLargeError(ValueError):
    """The stack would decode to more than the limits allow (HTTP 413)."""


def parse_z_list(text: str) -> np.ndarray:
    """z (um) from a form field: a JSON list or comma-separated numbers; ValueError if not."""
    text = text.strip()
    try:
        values = (
            json.loads(text)
            if text.startswith("[")
            else [float(part) for part in text.split(",") if part.strip()]
        )
        z = np.asarray(values, dtype=np.float64)
    # RecursionError: lists nested thousands deep, which the JSON parser recurses into
    except (ValueError, TypeError, RecursionError) as error:
        raise ValueError(f"z_um must be a JSON list or comma-separated numbers: {error}") from None
    if z.ndim != 1:
        raise ValueError(f"z_um must be a flat list of numbers, got shape {z.shape}")
    return z


def _check_size(
    shape: tuple[int, ...], itemsize: int, max_frames: int, max_decoded_bytes: int
) -> None:
    """Refuse a stack of `shape` before its pixels are decoded: too many frames or bytes, none."""
    if any(side == 0 for side in shape[1:]) or not shape:
        raise ValueError(f"the stack's frames have no pixels (shape {shape})")
    if shape[0] > max_frames:
        raise TooLargeError(f"the stack has {shape[0]} frames; the limit is {max_frames}")
    decoded = math.prod(shape) * itemsize
    if decoded > max_decoded_bytes:
        raise TooLargeError(
            f"the stack would decode to {decoded} bytes (shape {shape}); the limit is "
            f"{max_decoded_bytes} bytes"
        )


def _npy_shape(data: bytes) -> tuple[tuple[int, ...], int]:
    """The shape and item size a .npy file declares in its header (nothing else is read)."""
    buffer = io.BytesIO(data)
    version = np.lib.format.read_magic(buffer)
    readers = {
        (1, 0): np.lib.format.read_array_header_1_0,
        (2, 0): np.lib.format.read_array_header_2_0,
    }
    if version not in readers:
        raise ValueError(f".npy format version {version} is not supported (1.0 or 2.0)")
    shape, _, dtype = readers[version](buffer)  # a header over 10 000 bytes: ValueError
    return tuple(int(side) for side in shape), dtype.itemsize


def _read_tiff(data: bytes, max_frames: int, max_decoded_bytes: int) -> np.ndarray:
    """The pages of a TIFF, once their count and the largest page's shape and item size, read
    from the TIFF's tags alone, are within the limits (TooLargeError)."""
    import tifffile  # imported on first use, not at start-up

    with tifffile.TiffFile(io.BytesIO(data)) as tiff:
        n_pages, itemsize = 0, 1
        largest: tuple[int, ...] = (0,)
        for page in tiff.pages:
            n_pages += 1
            if n_pages > max_frames:
                break
            shape = tuple(int(side) for side in page.shape)
            if math.prod(shape) >= math.prod(largest):
                largest, itemsize = shape, np.dtype(page.dtype).itemsize
    _check_size((n_pages, *largest), itemsize, max_frames, max_decoded_bytes)
    return tifffile.imread(io.BytesIO(data))


def decode_stack(data: bytes, max_frames: int, max_decoded_bytes: int) -> np.ndarray:
    """A z-stack from the bytes of a .npy or (multi-page) TIFF file; ValueError if it is not.

    At most `max_frames` frames and `max_decoded_bytes` bytes once decoded (TooLargeError,
    checked from the file's header before decoding); UnsupportedFileError for a file that
    is neither.
    """
    if data.startswith(_NPY_MAGIC):
        try:
            _check_size(*_npy_shape(data), max_frames, max_decoded_bytes)
            return np.load(io.BytesIO(data), allow_pickle=False)
        except ValueError as error:
            if isinstance(error, TooLargeError):
                raise
            raise ValueError(f"the .npy file cannot be read: {error}") from None
    if data[:4] in _TIFF_MAGICS:
        try:
            return _read_tiff(data, max_frames, max_decoded_bytes)
        except TooLargeError:
            raise
        except Exception as error:  # tifffile raises many types on a broken file
            raise ValueError(f"the TIFF file cannot be read: {error}") from None
    raise UnsupportedFileError(
        "the stack must be a multi-page TIFF or a .npy file (unknown file signature)"
    )
