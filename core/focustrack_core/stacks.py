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
import struct
import threading
from tokenize import TokenError
from typing import Any

import numpy as np

from focustrack_core.serving import cut

_NPY_MAGIC = b"\x93NUMPY"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
#: The longest .npy header read, bytes (numpy's own limit for untrusted files).
MAX_NPY_HEADER_BYTES = 10_000


class UnsupportedFileError(ValueError):
    """The upload is neither a TIFF nor a .npy file (HTTP 415)."""


class TooLargeError(ValueError):
    """The stack would decode to more than the limits allow (HTTP 413)."""


def parse_z_list(text: str) -> np.ndarray:
    """z (um) from a form field: a JSON list of finite numbers, its brackets optional
    (``-1, 0, 2.5``); ValueError naming the first item that is not one. JSON's numbers,
    not Python's: ``1_0`` and full-width digits, which `float` reads, are refused, as are
    ``true``, strings, nested lists and numbers past float64 (``1e400``, 400 digits)."""
    text = text.strip()
    try:
        values = json.loads(text if text.startswith("[") else f"[{text}]")
    except RecursionError:  # lists nested thousands deep, which the parser recurses into
        raise ValueError("z_um must be a flat list of numbers; it nests lists deeply") from None
    except ValueError as error:
        # The parser's own message only gives the column it stopped at: name the item.
        items = text.removeprefix("[").removesuffix("]").split(",")
        bad = next((item.strip() for item in items if not _finite_number(_json_value(item))), None)
        if bad is None or any(bracket in bad for bracket in "[]{}"):
            raise ValueError(
                f"z_um must be a JSON list or comma-separated numbers: {cut(str(error))}"
            ) from None
        raise ValueError(
            "z_um must be finite numbers (um), a JSON list or comma-separated: "
            f"{cut(bad)!r} is not one"
        ) from None
    for value in values:
        if isinstance(value, list | dict):
            raise ValueError(f"z_um must be a flat list of numbers; got {cut(json.dumps(value))}")
        if isinstance(value, bool | str) or value is None:
            raise ValueError(f"z_um must list numbers; got {cut(repr(value))}")
        if not _finite_number(value):
            raise ValueError(f"z_um must be finite numbers (um); got {cut(str(value))}")
    return np.array(values, dtype=np.float64)


def _finite_number(value: object) -> bool:
    """Whether `value` is one finite number: not a boolean, NaN or Infinity (JSON
    extensions that Python reads), or an integer too large for float64."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer of over 308 digits
        return False


def _json_value(text: str) -> object:
    """The value the JSON `text` gives, None where it is not JSON."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError):
        return None


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
    # A header may declare sides of hundreds of digits: the numbers said are cut.
    if len(shape) > 2 and shape[0] > max_frames:
        raise TooLargeError(
            f"the stack has {cut(str(shape[0]), 40)} frames; the limit is {max_frames}"
        )
    decoded = math.prod(shape) * itemsize
    if decoded > max_decoded_bytes:
        raise TooLargeError(
            f"the stack would decode to {cut(str(decoded), 40)} bytes (shape "
            f"{cut(str(shape))}); the limit is {max_decoded_bytes} bytes"
        )


def npy_header(data: bytes) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype the .npy file `data` declares in its header (nothing else is
    read: a header may promise more than any memory holds; `npy_array` reads the array).

    ValueError, in our words rather than numpy's, for a header over MAX_NPY_HEADER_BYTES
    or one numpy cannot parse, a negative side, an array of Python objects (a pickle, never
    loaded), or bytes beyond the data it declares (a file written twice over, or two
    joined: the rest used to be left unread, silently).
    """
    shape, dtype, _ = _npy_layout(data)
    return shape, dtype


def npy_array(data: bytes) -> np.ndarray:
    """The array of the .npy file `data`, once `npy_header` has shown it is one of a size
    to read; ValueError for data cut short (numpy's words: "EOF: reading array data,
    expected 65536 bytes got 65436")."""
    shape, dtype, data_offset = _npy_layout(data)
    declared = data_offset + math.prod(shape) * dtype.itemsize
    if len(data) < declared:
        raise ValueError(
            f"it is cut short: {len(data)} bytes of the {declared} that its header and "
            f"{shape} array of {dtype} take"
        )
    return np.load(io.BytesIO(data), allow_pickle=False)


def _npy_layout(data: bytes) -> tuple[tuple[int, ...], np.dtype, int]:
    """The shape, dtype and data offset (bytes) of the .npy file `data` (`npy_header`)."""
    buffer = io.BytesIO(data)
    version = np.lib.format.read_magic(buffer)
    length_formats = {(1, 0): "<H", (2, 0): "<I"}  # the header's length, after the magic
    if version not in length_formats:
        raise ValueError(f".npy format version {version} is not supported (1.0 or 2.0)")
    length_format = length_formats[version]
    header_start = buffer.tell() + struct.calcsize(length_format)
    if len(data) < header_start:
        raise ValueError(f"it is cut short within its header ({len(data)} bytes in all)")
    (header_bytes,) = struct.unpack_from(length_format, data, buffer.tell())
    if header_bytes > MAX_NPY_HEADER_BYTES:  # numpy's words: "... use allow_pickle=True"
        raise ValueError(
            f"its header is {header_bytes} bytes long; at most {MAX_NPY_HEADER_BYTES} are "
            "read (a plain array's header takes under 200)"
        )
    if len(data) < header_start + header_bytes:  # numpy's words: "EOF: ... expected 80 bytes"
        raise ValueError(
            f"it is cut short within its header ({len(data)} bytes in all, the header ends "
            f"at byte {header_start + header_bytes})"
        )
    reader = np.lib.format.read_array_header_1_0
    if version == (2, 0):
        reader = np.lib.format.read_array_header_2_0
    try:
        shape, _, dtype = reader(buffer, max_header_size=MAX_NPY_HEADER_BYTES)
    except (SyntaxError, TokenError) as error:  # an unclosed bracket or quote in the header
        raise ValueError(f"its header is not a Python literal ({error})") from None
    except ValueError as error:
        if str(error).startswith("malformed node"):  # literal_eval's: "<ast.BinOp at 0x..>"
            raise ValueError(
                "its header is not a Python literal (it holds an expression)"
            ) from None
        raise ValueError(f"its header is not a .npy array's ({cut(str(error))})") from None
    shape = tuple(int(side) for side in shape)
    if any(side < 0 for side in shape):
        raise ValueError(f"its header declares a negative side (shape {shape})")
    if dtype.hasobject:  # numpy's words: "Object arrays cannot be loaded when allow_pickle=False"
        raise ValueError(
            f"it holds Python objects (dtype {dtype}, stored as a pickle), which are never "
            "loaded: save the counts as numbers"
        )
    data_offset = buffer.tell()
    declared = data_offset + math.prod(shape) * dtype.itemsize
    if len(data) > declared:
        raise ValueError(
            f"it holds {len(data) - declared} bytes beyond the {shape} array its header declares"
        )
    return shape, dtype, data_offset


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
        try:
            frames = tiff.asarray(key=range(len(pages))).reshape(len(pages), *shape)
        except Exception as error:  # the codec's own words ("LIBDEFLATE_BAD_DATA"), framed
            raise ValueError(
                f"its pixels do not decode (cut short or damaged?): {cut(str(error))}"
            ) from None
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
            return npy_array(data)
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
