"""Heat maps as PNG files, with numpy and zlib only: no plotting library to import.

The map endpoint's PNG (`GET /v1/slides/{id}/map?format=png`) must come back
within a second of a restart; matplotlib's first import alone took seconds on a
loaded machine (and builds a font cache on a fresh one). A heat map needs none
of it: each layer is coloured through a colormap (viridis and magma, sampled
from matplotlib at nine points and interpolated linearly), scaled up to whole
pixels per tile, with a colour bar whose ends are labelled in a 3x5 pixel
digit font. The layers' names and the title go into the file's text chunks.
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np

#: matplotlib's viridis and magma at 0, 1/8, ..., 1 (RGB, 0-255).
VIRIDIS = np.array(
    [[68, 1, 84], [71, 45, 123], [59, 82, 139], [44, 114, 142], [33, 145, 140],
     [40, 174, 128], [94, 201, 98], [173, 220, 48], [253, 231, 37]],
    dtype=float,
)  # fmt: skip
MAGMA = np.array(
    [[0, 0, 4], [29, 17, 71], [81, 18, 124], [131, 38, 129], [183, 55, 121],
     [231, 82, 99], [252, 137, 97], [254, 196, 136], [252, 253, 191]],
    dtype=float,
)  # fmt: skip
MISSING_RGB = (190, 190, 190)  # tiles without an estimate (NaN)

#: Glyphs of the labels, 3 pixels wide and 5 high, row by row.
_GLYPHS = {
    "0": "111101101101111",
    "1": "010110010010111",
    "2": "111001111100111",
    "3": "111001111001111",
    "4": "101101111001001",
    "5": "111100111001111",
    "6": "111100111101111",
    "7": "111001001001001",
    "8": "111101111101111",
    "9": "111101111001111",
    ".": "000000000000010",
    "-": "000000111000000",
}
_FONT_SCALE = 2  # pixels per glyph pixel
_MARGIN = 8  # pixels around and between the panels
_BAR_WIDTH = 12
_PANEL_SIDE = 320  # pixels of a panel's longer side, at least 2 per tile


def colorize(values: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, float, float]:
    """RGB (..., 3) uint8 of `values` on the colormap `anchors` (n, 3), and its range.

    The range is the finite values' min and max (NaN when there are none); NaN
    is `MISSING_RGB`.
    """
    finite = np.isfinite(values)
    if not finite.any():
        return (
            np.broadcast_to(np.array(MISSING_RGB, np.uint8), (*values.shape, 3)),
            math.nan,
            math.nan,
        )
    low, high = float(values[finite].min()), float(values[finite].max())
    scaled = np.clip((values - low) / (high - low) if high > low else values * 0.0, 0.0, 1.0)
    stops = np.linspace(0.0, 1.0, len(anchors))
    rgb = np.stack([np.interp(scaled, stops, anchors[:, k]) for k in range(3)], axis=-1)
    rgb[~finite] = MISSING_RGB
    return np.round(rgb).astype(np.uint8), low, high


def _label(canvas: np.ndarray, text: str, top: int, left: int) -> None:
    """Draw `text` (digits, '.', '-') in black with its top-left corner at (top, left)."""
    for i, char in enumerate(text):
        glyph = np.array([bit == "1" for bit in _GLYPHS[char]]).reshape(5, 3)
        pixels = np.kron(glyph, np.ones((_FONT_SCALE, _FONT_SCALE), dtype=bool))
        x = left + i * 4 * _FONT_SCALE
        region = canvas[top : top + pixels.shape[0], x : x + pixels.shape[1]]
        region[pixels[: region.shape[0], : region.shape[1]]] = 0


def _number(value: float) -> str:
    return f"{value:.2f}" if math.isfinite(value) else "-"


def encode_png(rgb: np.ndarray, text: dict[str, str]) -> bytes:
    """A PNG file of an (height, width, 3) uint8 image, with `text` as tEXt chunks (Latin-1)."""
    height, width, _ = rgb.shape

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB
    scanlines = np.concatenate([np.zeros((height, 1), np.uint8), rgb.reshape(height, -1)], axis=1)
    chunks = [chunk(b"IHDR", header)]
    chunks += [
        chunk(b"tEXt", key.encode("latin-1") + b"\0" + value.encode("latin-1", "replace"))
        for key, value in text.items()
    ]
    chunks += [chunk(b"IDAT", zlib.compress(scanlines.tobytes(), 6)), chunk(b"IEND", b"")]
    return b"\x89PNG\r\n\x1a\n" + b"".join(chunks)


def heat_map_png(panels: list[tuple[str, np.ndarray, np.ndarray]], title: str) -> bytes:
    """Side-by-side heat maps of (name, values (rows, cols), colormap anchors) as a PNG.

    Row 0 at the top, column 0 at the left; each panel has a colour bar labelled
    with its range (top: max, bottom: min, in the values' unit). The title and
    the panels' names, left to right, are in the file's text chunks.
    """
    rows, cols = panels[0][1].shape
    scale = max(2, _PANEL_SIDE // max(rows, cols))
    image_h, image_w = rows * scale, cols * scale
    label_w = 10 * 4 * _FONT_SCALE
    glyph_h = 5 * _FONT_SCALE
    panel_w = image_w + _MARGIN + _BAR_WIDTH + _MARGIN + label_w
    height = max(image_h, 2 * glyph_h) + 2 * _MARGIN
    canvas = np.full((height, _MARGIN + len(panels) * panel_w, 3), 255, np.uint8)
    for i, (_, values, anchors) in enumerate(panels):
        left = _MARGIN + i * panel_w
        rgb, low, high = colorize(values, anchors)
        canvas[_MARGIN : _MARGIN + image_h, left : left + image_w] = np.repeat(
            np.repeat(rgb, scale, axis=0), scale, axis=1
        )
        bar_left = left + image_w + _MARGIN
        ramp = np.linspace(high, low, image_h)[:, None] * np.ones(_BAR_WIDTH)
        canvas[_MARGIN : _MARGIN + image_h, bar_left : bar_left + _BAR_WIDTH] = colorize(
            ramp, anchors
        )[0]
        label_left = bar_left + _BAR_WIDTH + 4
        _label(canvas, _number(high), _MARGIN, label_left)
        _label(canvas, _number(low), _MARGIN + max(image_h, 2 * glyph_h) - glyph_h, label_left)
    names = ", ".join(name for name, _, _ in panels)
    return encode_png(canvas, {"Title": title, "Description": f"left to right: {names}"})
