"""Is anything in view? One frame's structure against its pixel noise (a tile's look).

A scan that has just imaged empty glass looks at its next tile with one frame, at the
height the estimator predicts, before it takes a stack there: a stack of empty glass
costs its frames and says only what one frame could (`structure.structure_snr` needs the
change through focus, so two frames at least). One frame cannot tell focus from blur, but
it can tell structure from noise: a section even a few um out of focus keeps its nuclei
and fibres at scales of a few um, while empty glass holds pixel noise, an uneven
illumination (smooth across the frame) and the coverslip's dust, 10-170 um above the
section, blurred to the frame's scale or gone.

With P the preprocessed (low-passed) frame and B its Gaussian blur of `BACKGROUND_PX`
(px of P), the statistic is

    ratio = var(P - B) / (g sigma_n**2),

where sigma_n is the raw frame's pixel noise (`structure.pixel_noise_std`) and g the
variance the same two filters leave of unit white noise (measured once per shape): about
1 for empty glass, and its spread on pure noise at most sqrt(2 / (N g)) for N raw pixels,
as in `structure`. `look_snr` is the excess over 1 in units of that spread; a frame below
`MIN_LOOK_SNR` shows nothing to focus on.

`MIN_LOOK_SNR` was chosen on virtual slides of seeds 1 and 2 (256 px tiles, frames at the
section's height and 1.5 um and 4 um from it): empty glass without dust 0 +/- 1, with a
speck or a bubble's rim in view 27 to 29, tiles with tissue (0.3% of their area and more)
167 and more within 1.5 um of focus (17 at 4 um for 0.5% of tissue). A tissue tile taken
for glass would be imaged at its prediction unmeasured, a glass tile taken for tissue
costs a stack: the threshold lies nearer the glass.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from focustrack_focus import filters
from focustrack_focus.preprocess import Preprocess, lowpass
from focustrack_focus.structure import pixel_noise_std, unit_noise_patch

#: Sigma (px of the low-passed frame) of the blur whose removal leaves the scales a section
#: shows out of focus, without the illumination's slow changes or the coverslip's blurred dust.
BACKGROUND_PX = 8.0
#: A look whose structure stands less than this many noise spreads above its pixel noise
#: sees empty glass (the module docstring says how it was chosen).
MIN_LOOK_SNR = 60.0


def _band(image: np.ndarray) -> np.ndarray:
    return image - filters.BACKEND.gaussian_blur(image, BACKGROUND_PX)


@functools.lru_cache(maxsize=16)
def _band_noise_gain(shape: tuple[int, int], sigma_px: float, levels: int) -> float:
    """Variance the low-pass and `_band` leave of unit white noise on `shape` frames (seed 0)."""
    return float(_band(lowpass(unit_noise_patch(shape), sigma_px, levels)).var())


def look_snr(image: np.ndarray, raw: np.ndarray, preprocess: Preprocess) -> float:
    """How far one frame's structure stands above its noise (module docstring).

    image: the preprocessed frame (h, w) float32; raw: the 2-D crop it came from.
    Infinity where the frame shows no pixel noise (the test cannot judge it).
    """
    noise_std = pixel_noise_std(raw)
    gain = _band_noise_gain(raw.shape, preprocess.lowpass_sigma_px, preprocess.pyramid_levels)
    if noise_std == 0.0 or gain == 0.0:
        return math.inf
    _, std = filters.BACKEND.mean_std(_band(image))
    ratio = std**2 / (gain * noise_std**2)
    spread = math.sqrt(2.0 / (raw.shape[0] * raw.shape[1] * gain))
    return (ratio - 1.0) / spread
