"""The second pass's first-frame check: is a tile's one frame as sharp as the first pass's image?

On a second pass (``focustrack scan --first-pass DIR``) most tiles are imaged once, at the
estimator's prediction, without a measurement: the risk rule holds them in focus but for a
stated tail (`lean.choose_stack`). The scheduler holds the first pass's in-focus image of
every tile (`realign.FirstPassImages`); a frame taken off focus is less sharp than it. So
each such frame's sharpness is divided by the first pass's image's, on the part of the
tile both show once the pass's lateral offset is taken off (`sharpness_ratio`); below
`min_ratio` (`out_of_focus`) the frame is out of focus and the estimator is told so
(`Measurement.frame_out_of_focus`): it measures the tile with a stack, as any other.

Sharpness is Brenner's gradient over the mean squared (`sharpness`): the contrast of
detail two pixels across, which defocus takes first. On the simulator's 60x / 0.85 tissue
slide (depth of field 0.89 um) a frame 0.2 um off focus keeps 95% of it, 0.3 um 90%,
0.445 um (half the depth of field) 80%, 0.6 um 69%, with camera noise moving it by about
0.1% at 256 x 256 px: the ratio tells a frame beyond the depth of field from one within it,
whatever the specimen, up to how far off the first pass's image itself was (its kept frame
is the stack's frame nearest its focus, up to half a z step away).

Pure: grey images (height, width) in, numbers out.
"""

from __future__ import annotations

import numpy as np

from focustrack_scheduler.lateral import shared_parts

#: The default `min_ratio` (`focustrack scan --frame-check-ratio`): chosen with `focustrack
#: bench drift`'s second pass on seeds 4000-4002 (docs/drift.md), not the seeds it reports.
MIN_SHARPNESS_RATIO = 0.94

#: The fewest pixels a side of the part both images show may have to be compared.
MIN_SHARED_PX = 16

_TINY = float(np.finfo(np.float64).tiny)


def sharpness(image: np.ndarray) -> float:
    """Brenner's gradient of a grey image (height, width), both directions, over its mean
    squared: mean((I(x + 2) - I(x))^2) + the same along y, divided by mean(I)^2 (unitless, a
    contrast: unchanged by the frame's brightness)."""
    image = np.asarray(image, dtype=np.float64)
    dx = image[:, 2:] - image[:, :-2]
    dy = image[2:, :] - image[:-2, :]
    return float((np.mean(dx * dx) + np.mean(dy * dy)) / max(float(image.mean()) ** 2, _TINY))


def sharpness_ratio(frame: np.ndarray, reference: np.ndarray, shift_px: tuple[int, int]) -> float:
    """The sharpness of `frame` over that of `reference` (grey, one 2-D shape), on the part
    both show: a feature at pixel p of `reference` lies at p + `shift_px` (dy, dx; whole
    pixels) in `frame`. A ValueError where the shapes differ or the shared part is smaller
    than `MIN_SHARED_PX` on a side; a `reference` without detail gives infinity."""
    if frame.shape != reference.shape or frame.ndim != 2:
        raise ValueError(f"two grey images of one shape, got {frame.shape} and {reference.shape}")
    rows, cols = frame.shape
    if min(rows - abs(shift_px[0]), cols - abs(shift_px[1])) < MIN_SHARED_PX:
        raise ValueError(f"a shift of {shift_px} px leaves too little of {frame.shape} shared")
    shared_reference, shared_frame = shared_parts(reference, frame, shift_px)
    reference_sharpness = sharpness(shared_reference)
    if reference_sharpness <= 0.0:
        return float("inf")
    return sharpness(shared_frame) / reference_sharpness


def out_of_focus(ratio: float, min_ratio: float) -> bool:
    """Whether a frame whose sharpness is `ratio` times the first pass's image's is out of
    focus: below `min_ratio` (0 never is)."""
    return ratio < min_ratio
