"""PNG heat maps without a plotting library: a valid file, the colours where the values are."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from focustrack_estimator.heatmap import MAGMA, MISSING_RGB, VIRIDIS, colorize, heat_map_png


def _decode(png: bytes) -> tuple[np.ndarray, dict[str, str]]:
    """The RGB pixels and text chunks of a PNG written by `encode_png` (filter 0 lines)."""
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    position, data, text = 8, b"", {}
    width = height = 0
    while position < len(png):
        length = int.from_bytes(png[position : position + 4], "big")
        kind, body = png[position + 4 : position + 8], png[position + 8 : position + 8 + length]
        crc = int.from_bytes(png[position + 8 + length : position + 12 + length], "big")
        assert zlib.crc32(kind + body) == crc
        if kind == b"IHDR":
            width, height = int.from_bytes(body[:4], "big"), int.from_bytes(body[4:8], "big")
            assert body[8:10] == b"\x08\x02"  # 8-bit RGB
        elif kind == b"tEXt":
            key, value = body.split(b"\0")
            text[key.decode()] = value.decode("latin-1")
        elif kind == b"IDAT":
            data += body
        position += 12 + length
    lines = np.frombuffer(zlib.decompress(data), np.uint8).reshape(height, 1 + 3 * width)
    assert (lines[:, 0] == 0).all()
    return lines[:, 1:].reshape(height, width, 3), text


def test_colorize_spans_the_colormap_and_greys_out_nan() -> None:
    rgb, low, high = colorize(np.array([[2.0, 4.0], [np.nan, 3.0]]), VIRIDIS)
    assert (low, high) == (2.0, 4.0)
    assert tuple(rgb[0, 0]) == tuple(VIRIDIS[0]) and tuple(rgb[0, 1]) == tuple(VIRIDIS[-1])
    assert tuple(rgb[1, 0]) == MISSING_RGB
    assert tuple(rgb[1, 1]) == tuple(VIRIDIS[4])  # the middle anchor


def test_the_heat_map_png_shows_each_tile_in_its_colour() -> None:
    values = np.arange(12.0).reshape(3, 4)
    values[1, 2] = np.nan
    png = heat_map_png([("a_um", values, VIRIDIS), ("b_um", np.full((3, 4), np.nan), MAGMA)], "t")
    image, text = _decode(png)
    assert text == {"Title": "t", "Description": "left to right: a_um, b_um"}
    scale = 320 // 4  # pixels per tile: the longer side is 320 pixels
    top_left = 8  # the margin

    def tile(row: int, col: int) -> tuple[int, ...]:
        centre = (top_left + row * scale + scale // 2, top_left + col * scale + scale // 2)
        return tuple(int(v) for v in image[centre])

    assert tile(0, 0) == tuple(VIRIDIS[0])
    assert tile(2, 3) == tuple(VIRIDIS[-1])
    assert tile(1, 2) == MISSING_RGB
    assert image.shape[0] == 3 * scale + 2 * 8


@pytest.mark.parametrize("shape", [(1, 1), (200, 200), (7, 500)])
def test_any_grid_renders(shape: tuple[int, int]) -> None:
    image, _ = _decode(heat_map_png([("a_um", np.zeros(shape), VIRIDIS)], "slide"))
    assert image.shape[0] >= 2 * shape[0] and image.shape[1] >= 2 * shape[1]
