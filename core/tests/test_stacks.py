"""Uploaded z-stacks: .npy and TIFF read back, everything else refused with the right error,
too large a stack refused from its header before it is decoded."""

from __future__ import annotations

import io

import numpy as np
import pytest
import tifffile

from focustrack_core.stacks import TooLargeError, UnsupportedFileError, decode_stack, parse_z_list

STACK = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
ROOMY = {"max_frames": 10, "max_decoded_bytes": 1 << 20}


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def tiff_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, array, photometric="minisblack")
    return buffer.getvalue()


def npy_header_only(shape: tuple[int, ...]) -> bytes:
    """A .npy file that declares a uint16 array of `shape` and holds none of its pixels."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buffer, {"descr": "<u2", "fortran_order": False, "shape": shape}
    )
    return buffer.getvalue()


@pytest.mark.parametrize("encode", [npy_bytes, tiff_bytes])
def test_npy_and_tiff_read_back(encode) -> None:
    np.testing.assert_array_equal(decode_stack(encode(STACK), **ROOMY), STACK)


def test_a_tiff_written_a_page_at_a_time_is_every_page() -> None:
    """tifffile makes each such page a series of its own; each is still a frame."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tiff:
        for frame in STACK:
            tiff.write(frame)
    np.testing.assert_array_equal(decode_stack(buffer.getvalue(), **ROOMY), STACK)


@pytest.mark.parametrize("planarconfig", ["contig", "separate"])
def test_colour_frames_are_frames_first_samples_last_however_stored(planarconfig: str) -> None:
    """Colour planes stored apart were read (pages, samples, H, W): 5 RGB frames of 4x5 px
    came out as 5 frames of 3x4 px with 5 channels."""
    frames = np.arange(5 * 4 * 5 * 3, dtype=np.uint8).reshape(5, 4, 5, 3)
    stored = frames if planarconfig == "contig" else np.moveaxis(frames, -1, 1)
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, stored, photometric="rgb", planarconfig=planarconfig)
    np.testing.assert_array_equal(decode_stack(buffer.getvalue(), **ROOMY), frames)


def test_a_compressed_tiff_is_read() -> None:
    """LZW, as OpenCV writes a multi-page TIFF by default (imagecodecs decodes it)."""
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, STACK, photometric="minisblack", compression="lzw")
    np.testing.assert_array_equal(decode_stack(buffer.getvalue(), **ROOMY), STACK)


def test_a_one_page_tiff_is_one_frame() -> None:
    assert decode_stack(tiff_bytes(STACK[:1]), **ROOMY).shape == (1, 4, 5)


def test_tiff_pages_of_other_shapes_are_named() -> None:
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tiff:
        tiff.write(STACK[0])
        tiff.write(STACK[0, :, :4])
    with pytest.raises(ValueError, match=r"share one shape and type; got \(4, 4\) uint16, \(4, "):
        decode_stack(buffer.getvalue(), **ROOMY)


def test_a_tiff_whose_pages_loop_back_is_corrupt_not_long() -> None:
    data = bytearray(tiff_bytes(STACK))
    with tifffile.TiffFile(io.BytesIO(bytes(data))) as tiff:
        first, last = tiff.pages[0], tiff.pages[-1]
        next_at = last.offset + 2 + 12 * len(last.tags)  # classic TIFF: the IFD's last word
        data[next_at : next_at + 4] = first.offset.to_bytes(4, "little")
    with pytest.raises(ValueError, match="loop back") as caught:
        decode_stack(bytes(data), max_frames=1000, max_decoded_bytes=1 << 20)
    assert not isinstance(caught.value, TooLargeError)


def test_a_tiff_cut_short_is_damaged_not_its_first_pages() -> None:
    """tifffile reads the pages before the cut and says so only in its log."""
    frames = np.arange(10 * 64 * 64, dtype=np.uint16).reshape(10, 64, 64)
    data = tiff_bytes(frames)
    with pytest.raises(ValueError, match="damaged"):
        decode_stack(data[:-8000], **ROOMY | {"max_decoded_bytes": 1 << 22})


@pytest.mark.parametrize("shape", [(4096,), (300, 64)])
def test_an_array_of_fewer_dimensions_is_not_counted_in_frames(shape: tuple[int, ...]) -> None:
    """A flat array is no stack; a 2-D one is a single frame, however many its rows."""
    data = npy_bytes(np.zeros(shape, dtype=np.uint16))
    if len(shape) == 1:
        with pytest.raises(ValueError, match="frames of pixels") as caught:
            decode_stack(data, **ROOMY)
        assert not isinstance(caught.value, TooLargeError)
    else:
        assert decode_stack(data, **ROOMY).shape == shape


def test_other_files_are_unsupported() -> None:
    with pytest.raises(UnsupportedFileError, match="multi-page TIFF or a"):
        decode_stack(b"\x89PNG\r\n\x1a\n....", **ROOMY)


@pytest.mark.parametrize("encode", [npy_bytes, tiff_bytes])
def test_too_many_frames_or_bytes(encode) -> None:
    with pytest.raises(TooLargeError, match=r"(has 3|has more than 2) frames; the limit is 2"):
        decode_stack(encode(STACK), max_frames=2, max_decoded_bytes=1 << 20)
    with pytest.raises(TooLargeError, match="decode to 120 bytes"):
        decode_stack(encode(STACK), max_frames=10, max_decoded_bytes=119)


def test_a_header_promising_gigabytes_is_refused_unread() -> None:
    with pytest.raises(TooLargeError, match="the limit is 1048576 bytes"):
        decode_stack(npy_header_only((5, 8192, 8192)), **ROOMY)
    with pytest.raises(TooLargeError, match=r"\(cut: 402 characters in all\) bytes") as caught:
        decode_stack(npy_header_only((2, 8, 10**400)), **ROOMY)
    assert len(str(caught.value)) < 400  # the number said, not its 400 digits


@pytest.mark.parametrize(
    "data",
    [npy_bytes(STACK)[:-7], b"II*\x00" + bytes(20), npy_header_only((2, 0, 3)) + bytes(8)],
)
def test_broken_files_are_value_errors(data: bytes) -> None:
    with pytest.raises(ValueError, match="cannot be read") as caught:
        decode_stack(data, **ROOMY)
    assert not isinstance(caught.value, TooLargeError | UnsupportedFileError)


def test_a_compressed_tiff_cut_short_is_said_to_be_so() -> None:
    """The codec's words alone: "libdeflate_zlib_decompress returned LIBDEFLATE_BAD_DATA"."""
    buffer = io.BytesIO()
    noise = np.random.default_rng(0).integers(0, 4096, (3, 64, 64), dtype=np.uint16)
    tifffile.imwrite(buffer, noise, photometric="minisblack", compression="zlib")
    with pytest.raises(ValueError, match=r"its pixels do not decode \(cut short or damaged\?\)"):
        decode_stack(buffer.getvalue()[:-100], **ROOMY)


def test_an_array_of_python_objects_is_refused_in_our_words() -> None:
    """numpy's "Object arrays cannot be loaded when allow_pickle=False" named its own
    argument, not what is wrong with the file."""
    buffer = io.BytesIO()
    np.save(buffer, np.array([[[1, "a"]]], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"Python objects \(dtype object, stored as a pickle\)"):
        decode_stack(buffer.getvalue(), **ROOMY)


def _npy_with_header(header: bytes) -> bytes:
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(64)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (_npy_with_header(b"{'descr': '<u2', 'shape': (\n"), "its header is not a Python"),
        (_npy_with_header(b"{'descr': '<u2\n"), "its header is not a Python"),
        (npy_bytes(STACK) + npy_bytes(STACK), r"bytes beyond the \(3, 4, 5\) array"),
        # numpy's words named its own arguments, the AST, or its chunk sizes:
        (_npy_with_header(b"{" + b" " * 20_000), "header is 20001 bytes long; at most 10000"),
        (
            _npy_with_header(b"{'descr': '<u2', 'fortran_order': False, 'shape': (2, 2*3)}"),
            r"not a Python literal \(it holds an expression\)",
        ),
        (npy_header_only((2, -4, 5)) + bytes(8), r"negative side \(shape \(2, -4, 5\)\)"),
        (npy_bytes(STACK)[:-7], r"cut short: \d+ bytes of the \d+ that its header and"),
        (b"\x93NUMPY\x01\x00\x05", r"cut short within its header \(9 bytes in all\)"),
        (b"\x93NUMPY\x02\x00\x50\x00\x00\x00{", "the header ends at byte 92"),
    ],
)
def test_a_garbled_header_or_data_beyond_it_is_said_not_a_crash_or_ignored(
    data: bytes, why: str
) -> None:
    """An unclosed bracket in the header was a tokenizer error (a 500 in the services);
    bytes beyond the declared array were left unread, silently."""
    with pytest.raises(ValueError, match=why):
        decode_stack(data, **ROOMY)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("[-1, 0, 2.5]", [-1.0, 0.0, 2.5]), ("-1,0, 2.5", [-1.0, 0.0, 2.5]), ("[]", [])],
)
def test_z_lists(text: str, expected: list[float]) -> None:
    np.testing.assert_array_equal(parse_z_list(text), expected)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[1, 2", "JSON list"),
        ("1,a", "JSON list"),
        ("[[1, 2]]", "flat list"),
        ("[" * 100_000, "flat list of numbers; it nests lists deeply"),
        ("[" * 3000 + "]" * 3000, "it nests lists deeply"),  # "maximum recursion depth"
        ("[true, false, 1]", "must list numbers; got True"),
        ("true, 1, 2", "must list numbers; got True"),
        ("1_0, 2", "JSON list"),  # Python's float reads 10
        ("\uff11, 2", "JSON list"),  # a full-width 1, which float reads too
        ("1,,2", "JSON list"),
        ('[1, "2.5"]', "must list numbers; got '2.5'"),
        ("[1, null]", "must list numbers; got None"),
        ("1, inf", "'inf' is not one"),
        ("[1, NaN]", "must be finite numbers \\(um\\); got nan"),  # JSON extensions json reads
        ("[Infinity, 1]", "must be finite numbers \\(um\\); got inf"),
        (f"[0, 1{'0' * 400}]", "must be finite numbers \\(um\\); got 1000"),  # past float64
        (f"[0, 1{'0' * 5000}]", "'10000.*' is not one"),  # past Python's int parsing
        ('[1, {"z": 2}]', 'flat list of numbers; got {"z": 2}'),
    ],
)
def test_bad_z_lists(text: str, needle: str) -> None:
    with pytest.raises(ValueError, match=needle):
        parse_z_list(text)
