"""Preprocessing of a frame before a focus metric: channel, region of interest, low-pass.

Thesis Appendix A-1: a slide-scanner image is oversampled (0.04 um pixels
against a 0.39 um diffraction limit), so pixel-scale content is noise, and a
focus metric that sees it peaks out of focus. Low-pass filter first, with a
Gaussian matched to the optics, and never shrink the image with a plain
bilinear resize (it does not widen its kernel with the shrink factor and
aliases the noise back in). Giemsa-stained specimens have their contrast in
the green channel (A-1-2).

The Gaussian of `lowpass_sigma_px` is applied as an anti-aliased image
pyramid: each pyrDown (`filters`) is a 5-tap binomial low-pass (variance 1 px**2 at
its input scale) followed by decimation by 2, so L levels low-pass with
variance (4**L - 1) / 3 input px**2; the rest of the requested variance is a
small Gaussian at the reduced scale. Same low-pass, 4**L fewer pixels for the
metric to visit: that is what keeps the default pipeline above 100 frames/s
for 2048x2048 frames on one core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from focustrack_focus import filters

#: Index of the green channel in an RGB (or BGR) frame: the Giemsa channel.
GREEN = 1


def psf_sigma_um(na: float, wavelength_um: float) -> float:
    """Standard deviation in um of the Gaussian closest to the in-focus Airy PSF.

    sigma = 0.21 lambda / NA (Zhang, Zerubia & Olivo-Marin 2007, paraxial
    widefield fit). At NA 0.85 and 0.70 um (the longest visible wavelength, as
    in thesis A-1-1) that is 0.17 um.
    """
    if not (na > 0 and wavelength_um > 0):
        raise ValueError(f"NA and wavelength must be positive, got {na}, {wavelength_um} um")
    return 0.21 * wavelength_um / na


def lowpass_sigma_for_optics(pixel_um: float, na: float, wavelength_um: float = 0.70) -> float:
    """The low-pass sigma in px matched to the optics: the PSF width in pixels of the frame."""
    if not pixel_um > 0:
        raise ValueError(f"pixel size must be positive, got {pixel_um} um")
    return psf_sigma_um(na, wavelength_um) / pixel_um


#: The widest low-pass a request or the service's option may set, px: wider, no frame a
#: scanner takes keeps detail for a focus metric.
MAX_LOWPASS_SIGMA_PX = 64.0


@dataclass(frozen=True)
class Preprocess:
    """How to turn a raw frame into the 2-D float32 image a focus metric reads.

    channel: index of the colour channel of an (H, W, C) frame; None picks the
        channel with the highest contrast (coefficient of variation) per frame;
        ignored for (H, W) frames. Default: green (Giemsa).
    roi: (y0, x0, height, width) in px of the raw frame, or None for all of it.
    lowpass_sigma_px: Gaussian low-pass sigma in raw px (0: none).
    """

    channel: int | None = GREEN
    roi: tuple[int, int, int, int] | None = None
    lowpass_sigma_px: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lowpass_sigma_px) and self.lowpass_sigma_px >= 0):
            raise ValueError(f"low-pass sigma must be >= 0 px, got {self.lowpass_sigma_px}")
        if self.roi is not None and (min(self.roi[2:]) < 1 or min(self.roi[:2]) < 0):
            raise ValueError(f"roi (y0, x0, height, width) must be inside a frame, got {self.roi}")

    @property
    def pyramid_levels(self) -> int:
        """How many pyrDown levels fit inside the requested low-pass (`pyramid_levels_for`)."""
        return pyramid_levels_for(self.lowpass_sigma_px)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """Preprocess one frame, (H, W) or (H, W, C), any real dtype -> (h, w) float32."""
        return self.smooth(self.crop(frame))

    def crop(self, frame: np.ndarray) -> np.ndarray:
        """The channel and region of interest of a frame, at full resolution: a 2-D view.

        ValueError if it has no pixels, or too few for the low-pass (`MIN_SMOOTHED_PX`).
        """
        image = select_channel(self.region(frame), self.channel)
        smoothed_px = min(image.shape) // 2**self.pyramid_levels
        if smoothed_px < MIN_SMOOTHED_PX and self.lowpass_sigma_px > 0:
            raise ValueError(
                f"a low-pass of {self.lowpass_sigma_px:g} px is too large for "
                f"{image.shape[0]}x{image.shape[1]} px frames (it leaves {smoothed_px} px of "
                f"the {MIN_SMOOTHED_PX} needed): use a smaller lowpass_sigma_px or larger frames"
            )
        return image

    def region(self, frame: np.ndarray) -> np.ndarray:
        """The region of interest of a frame (H, W) or (H, W, C), every channel: a view.

        ValueError if it has no pixels or the region does not fit in it.
        """
        if frame.size == 0:
            raise ValueError(f"the frames have no pixels (shape {frame.shape})")
        if self.roi is None:
            return frame
        y0, x0, height, width = self.roi
        if y0 + height > frame.shape[0] or x0 + width > frame.shape[1]:
            raise ValueError(f"roi {self.roi} does not fit in a {frame.shape[:2]} frame")
        return frame[y0 : y0 + height, x0 : x0 + width]

    def smooth(self, image: np.ndarray) -> np.ndarray:
        """The low-pass of a cropped 2-D image: (H, W) -> about (H, W) / 2**levels, float32."""
        return lowpass(image, self.lowpass_sigma_px, self.pyramid_levels)


#: Fewest pixels per side a frame may keep after the low-pass's pyramid: the focus
#: metrics and the noise estimate of the structure test need a neighbourhood.
MIN_SMOOTHED_PX = 4


def select_channel(frame: np.ndarray, channel: int | None) -> np.ndarray:
    """One channel of an (H, W, C) frame (None: the highest-contrast one); (H, W) as is, and
    the only channel of an (H, W, 1) one (a monochrome camera's, whatever `channel` says)."""
    if frame.ndim == 2:
        return frame
    if frame.ndim != 3:
        raise ValueError(f"a frame is (H, W) or (H, W, C), got shape {frame.shape}")
    if frame.shape[2] == 1:
        return frame[:, :, 0]
    if channel is None:
        # Contrast as the coefficient of variation, on a 4x subsample: cheap, and
        # choosing a channel needs no pixel-level precision.
        sample = frame[::4, ::4].reshape(-1, frame.shape[2]).astype(np.float32)
        cv = sample.std(axis=0) / np.maximum(sample.mean(axis=0), np.finfo(np.float32).tiny)
        channel = int(np.argmax(cv))
    if not 0 <= channel < frame.shape[2]:
        raise ValueError(f"channel {channel} does not exist in a frame of shape {frame.shape}")
    return frame[:, :, channel]


def pyramid_levels_for(sigma_px: float) -> int:
    """How many pyrDown levels fit inside a Gaussian low-pass of `sigma_px` (px): L levels
    are a binomial low-pass of variance (4**L - 1) / 3 px^2."""
    levels = 0
    while (4 ** (levels + 1) - 1) / 3 <= sigma_px**2:
        levels += 1
    return levels


def lowpass(image: np.ndarray, sigma_px: float, levels: int) -> np.ndarray:
    """Gaussian low-pass of `sigma_px` (input px) as `levels` pyrDowns plus a residual Gaussian.

    Returns float32 of shape about (H / 2**levels, W / 2**levels).
    """
    if image.dtype not in (np.uint8, np.uint16, np.float32):
        image = image.astype(np.float32)
    backend = filters.BACKEND
    for _ in range(levels):
        if min(image.shape) < 2:
            break
        image = backend.pyr_down(image)  # binomial low-pass, then keep every second pixel
    image = image.astype(np.float32, copy=False)
    residual_var_px2 = sigma_px**2 - (4**levels - 1) / 3
    residual_sigma = math.sqrt(max(residual_var_px2, 0.0)) / 2**levels
    if residual_sigma > 0.2:  # below that the 3-tap kernel is the identity to 1e-5
        image = backend.gaussian_blur(image, residual_sigma)
    return image
