"""Z-stacks uploaded to a REST service: a .npy or multi-page TIFF file, and its heights.

The focus and phase services take the same uploads, so they read them here, with the same
limits and the same errors: `UnsupportedFileError` (HTTP 415) for a file that is neither,
`TooLargeError` (413) for one that would decode to more than the limits allow, checked
from the file's header before its pixels are decoded (a 3.5 MB zlib TIFF can hold
3.6 GB), and ValueError (422) for the rest. TIFF files need tifffile, and compressed ones
(LZW, as OpenCV writes them, JPEG, zstd) imagecodecs (both in the services' ``service``
extras), imported on the first TIFF, not at start-up.
"""

from __future__ import annotations

import io
import json
import logging
import math
import threading
from tokenize import TokenError
from typing import Any

import numpy as np

_NPY_MAGIC = b"\x93NUMPY"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


class UnsupportedFileError(ValueError):
    """The upload is neither a TIFF nor a .npy file (HTTP 415)."""


class TooLargeError(ValueError):
    """The stack would decode to more than the limits allow (HTTP 413)."""


def parse_z_list(text: str) -> np.ndarray:
    """z (um) from a form field: a JSON list of numbers, its brackets optional (``-1, 0,
    2.5``); ValueError if not. JSON's numbers, not Python's: ``1_0`` and full-width digits,
    which `float` reads, are refused, as are ``true`` and strings, which numpy would read."""
    text = text.strip()
    try:
        values = json.loads(text if text.startswith("[") else f"[{text}]")
        z = np.asarray(values, dtype=np.float64)
    # RecursionError: lists nested thousands deep, which the JSON parser recurses into
    except (ValueError, TypeError, RecursionError) as error:
        raise ValueError(f"z_um must be a JSON list or comma-separated numbers: {error}") from None
    if z.ndim != 1:
        raise ValueError(f"z_um must be a flat list of numbers, got shape {z.shape}")
    not_numbers = [value for value in values if isinstance(value, bool | str)]
    if not_numbers:
        raise ValueError(f"z_um must list numbers; got {not_numbers[0]!r}")
    return z


def _check_size(
    shape: tuple[int, ...], itemsize: int, max_frames: int, max_decoded_bytes: int
) -> None:
    """Refuse a stack of `shape` before its pixels are decoded: too many frames or bytes, none.

    A 2-D array is one frame (height, width); more dimensions are frames first.
    """
    if len(shape) < 2:
        raise ValueError(
            f"the stack must be frames of pixels, (frames, height, width); got shape {shape}"
        )
    if any(side == 0 for side in shape[1:]):
        raise ValueError(f"the stack's frames have no pixels (shape {shape})")
    if len(shape) > 2 and shape[0] > max_frames:
        raise TooLargeError(f"the stack has {shape[0]} frames; the limit is {max_frames}")
    decoded = math.prod(shape) * itemsize
    if decoded > max_decoded_bytes:
        raise TooLargeError(
            f"the stack would decode to {decoded} bytes (shape {shape}); the limit is "
            f"{max_decoded_bytes} bytes"
        )


def npy_header(data: bytes) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype the .npy file `data` declares in its header (nothing else is
    read: a header may promise more than any memory holds).

    ValueError for a header numpy cannot parse, an array of Python objects (a pickle, never
    loaded), or bytes beyond the data it declares (a file written twice over, or two
    joined: the rest used to be left unread, silently).
    """
    buffer = io.BytesIO(data)
    version = np.lib.format.read_magic(buffer)
    readers = {
        (1, 0): np.lib.format.read_array_header_1_0,
        (2, 0): np.lib.format.read_array_header_2_0,
    }
    if version not in readers:
        raise ValueError(f".npy format version {version} is not supported (1.0 or 2.0)")
    try:
        shape, _, dtype = readers[version](buffer)  # a header over 10 000 bytes: ValueError
    except (SyntaxError, TokenError) as error:  # an unclosed bracket or quote in the header
        raise ValueError(f"its header is not a Python literal ({error})") from None
    shape = tuple(int(side) for side in shape)
    if dtype.hasobject:  # numpy's words: "Object arrays cannot be loaded when allow_pickle=False"
        raise ValueError(
            f"it holds Python objects (dtype {dtype}, stored as a pickle), which are never "
            "loaded: save the counts as numbers"
        )
    declared = buffer.tell() + math.prod(shape) * dtype.itemsize
    if len(data) > declared:
        raise ValueError(
            f"it holds {len(data) - declared} bytes beyond the {shape} array its header declares"
        )
    return shape, dtype


class _Complaints(logging.Handler):
    """The errors tifffile logs on this thread while it reads a file. Where a file is cut
    short, tifffile reads the pages before the damage and says so only in its log."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.thread = threading.get_ident()  # the services read uploads on several threads
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage())


def _read_tiff(data: bytes, max_frames: int, max_decoded_bytes: int) -> np.ndarray:
    """`_read_pages`, refused (ValueError) where tifffile logs an error as it reads: a
    truncated file would otherwise be the frames before the cut."""
    complaints = _Complaints()
    logger = logging.getLogger("tifffile")
    logger.addHandler(complaints)
    try:
        frames = _read_pages(data, max_frames, max_decoded_bytes)
    finally:
        logger.removeHandler(complaints)
    if complaints.messages:
        raise ValueError(f"it is damaged (cut short?): {complaints.messages[0]}")
    return frames


def _read_pages(data: bytes, max_frames: int, max_decoded_bytes: int) -> np.ndarray:
    """Every page of a TIFF, frames first: (pages, height, width) or (pages, height, width,
    samples), once the pages' count, shape and type, read from the TIFF's tags alone, are
    within the limits (TooLargeError) and the same on every page (ValueError).

    Each page is a frame, however a writer grouped them into series (one page at a time
    makes a series of each, which tifffile's `imread` would cut to the first), and its
    samples come last whether they were stored interleaved or as separate planes (which
    tifffile reads as (samples, height, width)).
    """
    import tifffile  # imported on first use, not at start-up

    with tifffile.TiffFile(io.BytesIO(data)) as tiff:
        pages: list[Any] = []  # TiffPage or TiffFrame
        offsets: set[int] = set()
        for page in tiff.pages:  # a file of millions of pages is refused at max_frames + 1
            if page.offset in offsets:  # tifffile would follow the loop to the limit
                raise ValueError("its pages loop back to an earlier one (a corrupt file)")
            if len(pages) == max_frames:
                raise TooLargeError(
                    f"the stack has more than {max_frames} frames; the limit is {max_frames}"
                )
            offsets.add(page.offset)
            pages.append(page)
        kinds = {(tuple(int(side) for side in page.shape), np.dtype(page.dtype)) for page in pages}
        if not kinds:
            raise ValueError("it has no pages")
        if len(kinds) > 1:
            described = ", ".join(sorted(f"{shape} {dtype}" for shape, dtype in kinds))
            raise ValueError(f"the TIFF's pages must share one shape and type; got {described}")
        ((shape, dtype),) = kinds
        _check_size((len(pages), *shape), dtype.itemsize, max_frames, max_decoded_bytes)
        frames = tiff.asarray(key=range(len(pages))).reshape(len(pages), *shape)
        if pages[0].axes.startswith("S"):  # colour planes stored apart: (samples, H, W) a page
            return np.moveaxis(frames, 1, -1)
        return frames


def decode_stack(data: bytes, max_frames: int, max_decoded_bytes: int) -> np.ndarray:
    """A z-stack from the bytes of a .npy or (multi-page) TIFF file; ValueError if it is not.

    At most `max_frames` frames and `max_decoded_bytes` bytes once decoded (TooLargeError,
    checked from the file's header before decoding); UnsupportedFileError for a file that
    is neither.
    """
    if data.startswith(_NPY_MAGIC):
        try:
            shape, dtype = npy_header(data)
            _check_size(shape, dtype.itemsize, max_frames, max_decoded_bytes)
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
