"""Is there anything to focus on? A stack's through-focus change against its pixel noise.

A field with nothing in it (an empty or sparse field on a small frame, plasma
only) still gives a focus curve: pure noise, with a maximum somewhere. Reading
the curve alone cannot always tell that apart from a weak peak, least of all
on a short stack (five frames leave no frames away from the peak to measure the
curve's noise on). The images can: if the field holds structure that focus
acts on, the sharpest and the blurriest frame of the stack differ by more than
their pixel noise.

With P the preprocessed (low-passed) frames, the statistic is

    ratio = var(P_sharpest - P_blurriest) / (2 g sigma_n**2)

where sigma_n is the pixel noise of the raw frame (`pixel_noise_std`) and g the
variance that the low-pass leaves of unit white noise (`lowpass_noise_gain`):
about 1 for pure noise, far above it for a field with cells. Its spread on
pure noise is at most sqrt(2 / (N g)) for N raw pixels (the effective number of
independent samples after the low-pass is about N g; checked by simulation,
where the spread is 0.75 of this bound); `structure_snr` is the excess over 1 in
units of that spread.

Static structure (uneven illumination, a scratch far from focus) is the same in
every frame and cancels in the difference: only what focus changes counts.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from focustrack_focus import filters
from focustrack_focus.peak import MAD_TO_SIGMA
from focustrack_focus.preprocess import Preprocess, lowpass

#: 3x3 Laplacian-of-differences kernel (Immerkaer 1996): zero on any locally linear
#: image, sum of squared weights 36, so on white noise of std s its output has std 6 s.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
_NOISE_KERNEL_NORM = 6.0
#: Side (px) of the central region the pixel noise is measured on: noise is the same
#: all over a frame, and 65 000 pixels give it to about a percent.
_NOISE_REGION_PX = 256
#: Side (px) of the white-noise patch the low-pass gain is measured on.
_GAIN_PATCH_PX = 256


def pixel_noise_std(image: np.ndarray) -> float:
    """Std of the pixel noise of a 2-D raw image, in its own units (0.0 if it has none).

    The robust spread (MAD) of Immerkaer's noise operator over the central
    region: the operator removes smooth image content, the median ignores the
    edges it leaves, and the blurriest frame of a stack has the fewest.
    """
    height, width = image.shape
    if min(height, width) < 3:
        return 0.0
    y0 = max((height - _NOISE_REGION_PX) // 2, 0)
    x0 = max((width - _NOISE_REGION_PX) // 2, 0)
    region = image[y0 : y0 + _NOISE_REGION_PX, x0 : x0 + _NOISE_REGION_PX].astype(np.float32)
    response = filters.BACKEND.correlate(region, _NOISE_KERNEL)[1:-1, 1:-1]
    return MAD_TO_SIGMA * float(np.median(np.abs(response))) / _NOISE_KERNEL_NORM


@functools.lru_cache(maxsize=16)
def lowpass_noise_gain(shape: tuple[int, int], sigma_px: float, levels: int) -> float:
    """Variance that `lowpass(., sigma_px, levels)` leaves of unit white noise on `shape` frames.

    Measured (once per shape and filter) on a patch of at most 256x256 px, seed 0:
    the pyramid's borders make it depend a little on the frame size.
    """
    return float(lowpass(unit_noise_patch(shape), sigma_px, levels).var())


def unit_noise_patch(shape: tuple[int, int]) -> np.ndarray:
    """Unit white noise (seed 0, float32) on a patch of `shape` frames, at most 256x256 px:
    what a filter's noise gain is measured on."""
    patch = (min(shape[0], _GAIN_PATCH_PX), min(shape[1], _GAIN_PATCH_PX))
    return np.random.default_rng(0).standard_normal(patch, dtype=np.float32)


def structure_snr(
    sharpest: np.ndarray, blurriest: np.ndarray, blurriest_raw: np.ndarray, preprocess: Preprocess
) -> float:
    """How far a stack's through-focus change stands above its noise (module docstring).

    sharpest, blurriest: the preprocessed frames with the highest and lowest
    score, (h, w) float32; blurriest_raw: the raw 2-D crop the latter came from.
    Returns (ratio - 1) / spread; infinity when the frames show no pixel noise
    (noise-free or coarsely quantised data: the test cannot judge them), minus infinity
    when even the sharpest frame is uniform (all black: exposure 0, a closed shutter).
    """
    noise_std = pixel_noise_std(blurriest_raw)
    shape = blurriest_raw.shape
    gain = lowpass_noise_gain(shape, preprocess.lowpass_sigma_px, preprocess.pyramid_levels)
    if noise_std == 0.0 and filters.BACKEND.mean_std(sharpest)[1] == 0.0:
        return -math.inf  # no frame shows anything: nothing in view (it read flat alone)
    if noise_std == 0.0 or gain == 0.0:  # gain 0: a frame the low-pass leaves one pixel of
        return math.inf
    _, std = filters.BACKEND.mean_std(sharpest - blurriest)
    ratio = std**2 / (2.0 * gain * noise_std**2)
    spread = math.sqrt(2.0 / (shape[0] * shape[1] * gain))
    return (ratio - 1.0) / spread
