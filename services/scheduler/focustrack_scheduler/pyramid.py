"""The mosaic's zoomed-out levels, as both mosaic files (OME-TIFF, OME-Zarr) hold them."""

from __future__ import annotations

import math

import numpy as np

#: Side of the TIFF tiles, and the smallest pyramid level written, in pixels.
TIFF_TILE_PX = 256


def n_levels(shape: tuple[int, ...]) -> int:
    """How many halvings of an image of `shape` (height, width, ...) stay at least a tile."""
    return max(0, math.floor(math.log2(min(shape[:2]) / TIFF_TILE_PX)))


def half(image: np.ndarray) -> np.ndarray:
    """`image` (height, width, channels) at half the size: each pixel the mean of 2x2 (a
    viewer's zoomed-out level without aliasing), rounded where the image holds integers."""
    height, width = (image.shape[0] // 2) * 2, (image.shape[1] // 2) * 2
    blocks = image[:height, :width].reshape(height // 2, 2, width // 2, 2, -1)
    mean = blocks.mean(axis=(1, 3))
    return (mean if np.issubdtype(image.dtype, np.floating) else mean.round()).astype(image.dtype)
