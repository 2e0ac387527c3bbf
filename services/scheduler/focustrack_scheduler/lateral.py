"""The lateral offset of a second pass: phase correlation of first- and second-pass tiles.

Between passes the stage's positions move by a few um (repeatability, thermal
expansion), so a second pass's tile (r, c) shows the specimen a few um away from
where the first pass's did. Its images are those of the first pass shifted by the
offset; phase correlation (the inverse transform of the normalised cross-power
spectrum, whose peak lies at the shift) measures it per tile, bounded to
`max_shift_px` (a peak farther out is a coincidence of the texture, not the stage),
refined to a fraction of a pixel by a parabola through the peak and its neighbours.
`pass_offset` combines several tiles (the median of the confident ones), so that a
flat or empty tile does not move the estimate. The z drift is kf-rescan's
(`focustrack_estimator.rescan`): the same first tiles measure both.

Pure: images in (2-D arrays of the same shape), shifts in pixels out: (dy, dx) is
where a feature of `reference` lies in `moving`, minus where it lay.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: A tile whose correlation peak stands less than this many standard deviations of the
#: correlation above its mean (within the bounds) is not used: too flat or too unlike the
#: first pass (an empty field, a fold) to say where it moved. Two 128-px tiles of one
#: specimen 30 px apart with camera noise: about 14 (21 not moved); unrelated tiles: about
#: 4 (the largest of a few thousand samples of noise).
MIN_SHARPNESS = 8.0


#: The least side of the part two tiles share for the second, finer correlation, px.
MIN_SHARED_PX = 32

#: The low-pass of the cross-power spectrum: its Gaussian's sigma, cycles per pixel.
LOW_PASS_CYCLES_PER_PX = 0.08


@dataclass(frozen=True)
class Shift:
    """A translation in pixels (rows, columns) and how sharp its correlation peak was: its
    height above the correlation's mean within the bounds, in standard deviations."""

    dy_px: float
    dx_px: float
    sharpness: float


def grey(image: np.ndarray) -> np.ndarray:
    """A frame (height, width[, channels]) as float grey (height, width): the channels' mean."""
    image = np.asarray(image, dtype=np.float64)
    return image.mean(axis=-1) if image.ndim == 3 else image


def parabola_vertex(minus: float, centre: float, plus: float) -> float:
    """The offset (-0.5..0.5) of a parabola's vertex through three equally spaced values."""
    curvature = minus - 2.0 * centre + plus
    if curvature >= 0:  # not a maximum: keep the sample
        return 0.0
    return float(np.clip(0.5 * (minus - plus) / curvature, -0.5, 0.5))


def shared_parts(
    reference: np.ndarray, moving: np.ndarray, shift_px: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The parts of `reference` and `moving` (one 2-D shape) that show the same place, where
    a feature at pixel p of `reference` lies at p + `shift_px` (dy, dx; whole pixels) in
    `moving`: (reference's, moving's), of one shape."""
    dy, dx = shift_px
    rows, cols = reference.shape
    return (
        reference[max(0, -dy) : rows - max(0, dy), max(0, -dx) : cols - max(0, dx)],
        moving[max(0, dy) : rows - max(0, -dy), max(0, dx) : cols - max(0, -dx)],
    )


def phase_shift(reference: np.ndarray, moving: np.ndarray, max_shift_px: float) -> Shift:
    """The shift of `moving` against `reference` (same shape, 2-D), at most `max_shift_px`
    in each axis; see the module docstring.

    Two steps: the whole tiles, then the part they share once the whole pixels of the
    first estimate are taken off, for the fraction (the window that keeps the edges from
    correlating also pulls a large shift towards zero; on the shared part the shift left
    is a fraction of a pixel, where it does not)."""
    coarse = _correlate(reference, moving, max_shift_px)
    iy, ix = round(coarse.dy_px), round(coarse.dx_px)
    rows, cols = reference.shape
    if min(rows - abs(iy), cols - abs(ix)) < MIN_SHARED_PX:
        return coarse
    fine = _correlate(*shared_parts(reference, moving, (iy, ix)), 2.0)
    return Shift(iy + fine.dy_px, ix + fine.dx_px, coarse.sharpness)


def _correlate(reference: np.ndarray, moving: np.ndarray, max_shift_px: float) -> Shift:
    """One phase correlation of two images of one shape, windowed (Hann), low-passed."""
    if reference.shape != moving.shape or reference.ndim != 2:
        raise ValueError(f"two images of one 2-D shape, got {reference.shape} and {moving.shape}")
    rows, cols = reference.shape
    window = np.outer(np.hanning(rows), np.hanning(cols))
    a = np.fft.rfft2((reference - reference.mean()) * window)
    b = np.fft.rfft2((moving - moving.mean()) * window)
    cross = b * np.conj(a)
    cross /= np.maximum(np.abs(cross), 1e-12)
    # Whitened, every frequency weighs alike, the noise-only high ones too: a low-pass keeps
    # the peak above their noise (and a few pixels wide, as the parabola needs).
    fy = np.fft.fftfreq(rows)[:, None]
    fx = np.fft.rfftfreq(cols)[None, :]
    cross *= np.exp(-(fx**2 + fy**2) / (2 * LOW_PASS_CYCLES_PER_PX**2))
    correlation = np.fft.irfft2(cross, s=reference.shape)
    dy = np.fft.fftfreq(rows, 1.0 / rows)[:, None]
    dx = np.fft.fftfreq(cols, 1.0 / cols)[None, :]
    inside = (np.abs(dy) <= max_shift_px) & (np.abs(dx) <= max_shift_px)
    masked = np.where(inside, correlation, -np.inf)
    i, j = np.unravel_index(int(np.argmax(masked)), masked.shape)
    peak = float(correlation[i, j])
    spread = float(correlation[inside].std())
    sharpness = (peak - float(correlation[inside].mean())) / spread if spread > 0 else 0.0
    sub_y = parabola_vertex(correlation[i - 1, j], peak, correlation[(i + 1) % rows, j])
    sub_x = parabola_vertex(correlation[i, j - 1], peak, correlation[i, (j + 1) % cols])
    return Shift(float(dy[i, 0]) + sub_y, float(dx[0, j]) + sub_x, sharpness)


def pass_offset(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]], max_shift_px: float
) -> Shift | None:
    """The second pass's offset from (first-pass tile, second-pass tile) pairs: the median
    shift of the tiles whose peak is at least `MIN_SHARPNESS` sharp, None if there is none."""
    return combined([phase_shift(first, second, max_shift_px) for first, second in pairs])


def combined(shifts: Sequence[Shift], min_confident: int = 1) -> Shift | None:
    """The median of the `shifts` whose peak is at least `MIN_SHARPNESS` sharp, None if
    fewer than `min_confident` are."""
    confident = [s for s in shifts if s.sharpness >= MIN_SHARPNESS]
    if len(confident) < max(min_confident, 1):
        return None
    return Shift(
        float(np.median([s.dy_px for s in confident])),
        float(np.median([s.dx_px for s in confident])),
        float(np.median([s.sharpness for s in confident])),
    )
