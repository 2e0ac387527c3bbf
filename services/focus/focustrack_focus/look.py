"""Is anything in view? One frame's stain against its pixel noise, at any defocus (a look).

A scan looks at a tile with one frame before it takes a stack there: a stack of empty glass
costs its frames and says only what one frame could. One frame cannot tell focus from blur,
and a section far out of focus loses its fine structure; but stained tissue absorbs light,
and a blur moves that light about without removing it, so even 10 um out of focus a field
with tissue in (or near) it keeps a coloured pattern of a few um, while clean glass is flat.
Coverslip dust and a bubble's rim are grey (they absorb every colour alike), and a grey
absorber changes the brightness of the channels, not their ratios. So the statistic reads
the frame's colour, not its brightness, at low spatial frequencies:

    with L_k = log(lowpass(I_k)) for each colour channel k (a Gaussian of `LOOK_SIGMA_PX`),
    c_k = L_k - mean_j L_j (the chroma: a grey absorber, an even illumination and the
    camera's white balance leave it flat), and c_k' = c_k minus its frame mean,

    ratio = sum_k var(c_k') / (g sum_k sum_j (delta_kj - 1/C)**2 r_j**2),

where r_j is channel j's relative pixel noise (`structure.pixel_noise_std` over its mean) and
g the variance the low-pass leaves of unit white noise (measured once per shape): about 1
for clean glass, with or without dust. A monochrome frame (one channel) has no chroma: c is
then L itself, and grey dust is something in view (it costs the tile a stack, not a wrong
frame). As in `structure`, its spread on pure noise is at most sqrt(2 / (N g)) for N raw
pixels; `look_snr` is the excess over 1 in units of that spread, and a frame below
`MIN_LOOK_SNR` shows nothing in view.

Chosen on virtual slides of seeds 1 and 2 (256 px tiles of 0.108 um, 10x10: every tile of
glass, every tile under 5% of tissue and a quarter of the others, frames 0 to 12 um from the
section either way): clean glass -2.1 to 2.7, glass with dust in view -0.3 to 2.1, tiles
with 0.2% to 1% of their area in section 266 and more within 4 um of focus and 20 and more
8 to 12 um away, fuller tiles 266 and more at any of these distances (`tests/test_look.py`
checks seeds 3 and 4, glass with its dust in focus included). A tissue tile taken for glass
would be imaged unmeasured, a glass tile taken for tissue costs a stack: the threshold lies
nearer the glass.

An unstained specimen (cells in culture, a smear's red cells read for phase) has no stain:
no colour at any defocus (a colour look reads it as grey dust). So the focus service
reading peaks in valley mode, as for such specimens, reads a look's brightness instead
(`brightness`: the channels' mean, as a monochrome frame). A phase object is faintest in
focus, but faint is not flat: its cells still move the light about well above the pixel
noise there, while glass leaves only the illumination's shading, which the low-pass
keeps and which errs the safe way (a stack). Measured with the threshold above: on the
simulator's red cells and cells in culture (10x10 tiles of 256 px, seeds 0 to 3, 0.8 um
below focus and in focus) glass scored at most 2.4 and the least covered tile with cells
(2 % of its area) 2023 in focus; the real yeast stack (`../shared/data/real`, 63x60 px,
full of cells) scores 148 at its focus, its lowest (7000 and more 5 um out).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from focustrack_focus.preprocess import lowpass, pyramid_levels_for
from focustrack_focus.structure import pixel_noise_std, unit_noise_patch

#: Sigma (raw px) of the low-pass the chroma is read at: a section's pattern out of focus
#: lives at a few um; the pixel noise averages out over this.
LOOK_SIGMA_PX = 16.0
#: Fewest px per side the low-passed frame keeps (a smaller frame gets a smaller sigma).
_MIN_SIDE_PX = 8
#: A look whose chroma stands less than this many noise spreads above its pixel noise sees
#: nothing in view (the module docstring says how it was chosen).
MIN_LOOK_SNR = 8.0


def _sigma_px(shape: tuple[int, int]) -> float:
    """The low-pass sigma for frames of `shape`: LOOK_SIGMA_PX, or less where the pyramid
    would leave fewer than _MIN_SIDE_PX px a side."""
    return min(LOOK_SIGMA_PX, min(shape) / (2 * _MIN_SIDE_PX))


@functools.lru_cache(maxsize=16)
def _noise_gain(shape: tuple[int, int], sigma_px: float) -> float:
    """Variance the look's low-pass leaves of unit white noise on `shape` frames (seed 0)."""
    return float(lowpass(unit_noise_patch(shape), sigma_px, pyramid_levels_for(sigma_px)).var())


def look_snr(region: np.ndarray, *, brightness: bool = False) -> float:
    """How far one frame's chroma (its brightness, for a monochrome frame or with
    `brightness`) stands above its pixel noise at low spatial frequencies (module
    docstring).

    region: the raw frame's region of interest, (h, w) or (h, w, C), every channel.
    Infinity where a channel shows no pixel noise or no light (the test cannot judge it).
    """
    if region.ndim == 3 and brightness:  # the channels' mean: one channel, its brightness
        region = region[:, :, :3].mean(axis=2, dtype=np.float32)
    channels = region[:, :, :3] if region.ndim == 3 else region[:, :, None]
    shape = (channels.shape[0], channels.shape[1])
    sigma_px = _sigma_px(shape)
    gain = _noise_gain(shape, sigma_px)
    logs, rel_var = [], []
    for k in range(channels.shape[2]):
        channel = np.ascontiguousarray(channels[:, :, k])
        noise_std, mean = pixel_noise_std(channel), float(channel.mean())
        if noise_std == 0.0 or mean <= 0.0 or gain == 0.0:
            return math.inf
        smooth = lowpass(channel, sigma_px, pyramid_levels_for(sigma_px))
        logs.append(np.log(np.maximum(smooth, np.float32(mean * 1e-3))))
        rel_var.append((noise_std / mean) ** 2)
    log_i = np.stack(logs)
    grey = 1.0 / len(logs) if len(logs) > 1 else 0.0  # one channel: its brightness
    chroma = log_i - grey * log_i.sum(axis=0)
    band_var = float(chroma.reshape(len(logs), -1).var(axis=1).sum())
    weights = (np.eye(len(logs)) - grey) ** 2
    noise_var = gain * float((weights @ np.array(rel_var)).sum())
    spread = math.sqrt(2.0 / (shape[0] * shape[1] * gain))
    return (band_var / noise_var - 1.0) / spread
