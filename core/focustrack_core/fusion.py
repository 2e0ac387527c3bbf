"""Extended depth of field: one image of a tile from the frames it keeps at several z.

Where one frame of a tile is too unsure to be in focus, the tile keeps several, a
depth of field apart (docs/lean.md); its image in the mosaic takes each pixel from
the frame that is sharpest around it. Sharpness is the local energy of the
Laplacian, the classic focus measure of extended-depth-of-field fusion (as in
Fiji's "Extended Depth of Field" and the slide scanners' extended-focus modes).
Pure numpy, in the core: the scheduler fuses its mosaic tiles with it and the lab
integrations (`focustrack_lab`) their MDA images, and neither has an image library.
"""

from __future__ import annotations

import numpy as np

#: Side of the square over which a pixel's sharpness is summed, in pixels: a few times
#: the blur of a frame a depth of field away, so that texture, not noise, decides.
WINDOW_PX = 9


def box_sum(image: np.ndarray, window_px: int) -> np.ndarray:
    """The sum of `image` (h, w) over a window_px square about each pixel (edges replicated)."""
    half = window_px // 2
    padded = np.pad(image, half + 1, mode="edge")
    summed = padded.cumsum(axis=0).cumsum(axis=1)
    h, w = image.shape
    top, bottom = summed[:h, :], summed[window_px : window_px + h, :]
    rows = bottom - top  # sums over window_px rows, shape (h, w + 2 half + 2)
    return rows[:, window_px : window_px + w] - rows[:, :w]


def sharpness(frame: np.ndarray, window_px: int = WINDOW_PX) -> np.ndarray:
    """Local focus measure of one frame (h, w[, channels]): the squared 4-neighbour
    Laplacian of its channel mean, summed over a window_px square, (h, w)."""
    grey = frame.astype(np.float64)
    if grey.ndim == 3:
        grey = grey.mean(axis=2)
    padded = np.pad(grey, 1, mode="edge")
    laplacian = (
        padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:] - 4.0 * grey
    )
    return box_sum(laplacian**2, window_px)


def fuse_planes(frames: np.ndarray, window_px: int = WINDOW_PX) -> np.ndarray:
    """One image (h, w[, channels]) from frames (n, h, w[, channels]) of one tile: each
    pixel from the frame sharpest about it (the first of equals); the frames' dtype."""
    if frames.ndim not in (3, 4) or frames.shape[0] == 0:
        raise ValueError(f"frames must be (n, h, w[, channels]) with n >= 1, got {frames.shape}")
    best = np.argmax(np.stack([sharpness(frame, window_px) for frame in frames]), axis=0)
    rows, cols = np.indices(best.shape)
    return frames[best, rows, cols]
