"""The image filters of the focus maths: OpenCV where it is installed, numpy and scipy otherwise.

OpenCV is an accelerator, not a dependency: the focus service installs it (extra
`service`), a lab's acquisition environment (`focustrack-lab`) need not. Both
backends give the same numbers (OpenCV's borders: reflect-101 is scipy's
`mirror`, OpenCV's `BORDER_REFLECT` scipy's `reflect`; `services/focus/tests/test_focus_filters.py`
checks them against each other). Per frame of the default pipeline, numpy/scipy
costs 5 to 8 times OpenCV's (`scripts/focus_frame_cost.py`, docs/benchmarks.md),
so the service keeps OpenCV. The one thing only OpenCV does is JPEG encoding (the
`jpeg_size` metric).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Protocol

import numpy as np


class Filters(Protocol):
    """What the focus maths asks of an image library; images are 2-D, shapes (h, w)."""

    name: str

    def mean(self, image: np.ndarray) -> float:
        """Mean of the pixels, accumulated in float64."""
        ...

    def mean_std(self, image: np.ndarray) -> tuple[float, float]:
        """Mean and (population) standard deviation of the pixels, accumulated in float64."""
        ...

    def pyr_down(self, image: np.ndarray) -> np.ndarray:
        """Binomial low-pass (reflect-101 borders), then every second pixel: (h, w) ->
        ((h + 1) // 2, (w + 1) // 2), the input's dtype (integers rounded half up)."""
        ...

    def gaussian_blur(self, image: np.ndarray, sigma_px: float) -> np.ndarray:
        """Gaussian of sigma_px on float32 (h, w), kernel radius as OpenCV's (4 sigma),
        mirrored borders (`BORDER_REFLECT`)."""
        ...

    def correlate(self, image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        """Correlation of float32 (h, w) with a small 2-D kernel, reflect-101 borders."""
        ...

    def jpeg_bytes(self, image: np.ndarray, scale: float, quality: int) -> int:
        """Size in bytes of float32 (h, w) times `scale`, clipped to 8 bits and
        JPEG-encoded at `quality`."""
        ...


class OpenCVFilters:
    """The filters with OpenCV (`cv2`): the service's backend."""

    name = "opencv"

    def __init__(self, cv2: ModuleType) -> None:
        self.cv2 = cv2

    def mean(self, image: np.ndarray) -> float:
        return float(self.cv2.mean(image)[0])

    def mean_std(self, image: np.ndarray) -> tuple[float, float]:
        mean, std = self.cv2.meanStdDev(image)
        return float(mean.item()), float(std.item())

    def pyr_down(self, image: np.ndarray) -> np.ndarray:
        return np.asarray(self.cv2.pyrDown(image))

    def gaussian_blur(self, image: np.ndarray, sigma_px: float) -> np.ndarray:
        cv2 = self.cv2
        return np.asarray(cv2.GaussianBlur(image, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT))

    def correlate(self, image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        return np.asarray(self.cv2.filter2D(image, self.cv2.CV_32F, kernel))

    def jpeg_bytes(self, image: np.ndarray, scale: float, quality: int) -> int:
        cv2 = self.cv2
        grey = cv2.convertScaleAbs(image, alpha=scale)
        ok, encoded = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise ValueError(f"JPEG encoding failed for a frame of shape {image.shape}")
        return int(encoded.size)


class ScipyFilters:
    """The filters with numpy and scipy.ndimage: the lab's backend, no OpenCV needed."""

    name = "scipy"

    def mean(self, image: np.ndarray) -> float:
        return float(image.mean(dtype=np.float64))

    def mean_std(self, image: np.ndarray) -> tuple[float, float]:
        return float(image.mean(dtype=np.float64)), float(image.std(dtype=np.float64))

    def pyr_down(self, image: np.ndarray) -> np.ndarray:
        # Separable: the taps at every second row, then (transposed) at every second column,
        # in numpy slices (3 times faster than scipy's correlate1d along the rows). The
        # integer sums (at most 16 bits x 256) are exact in float32, so integers round as
        # OpenCV's do.
        out = _binomial_half(_binomial_half(image.astype(np.float32)).T).T / 256
        if image.dtype.kind in "ui":
            return np.floor(out + 0.5).astype(image.dtype)  # OpenCV rounds half up
        return out

    def gaussian_blur(self, image: np.ndarray, sigma_px: float) -> np.ndarray:
        from scipy.ndimage import gaussian_filter

        # OpenCV's kernel size for a float image: round(8 sigma + 1), made odd.
        radius_px = (round(8 * sigma_px + 1) | 1) // 2
        return np.asarray(gaussian_filter(image, sigma_px, mode="reflect", radius=radius_px))

    def correlate(self, image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
        from scipy.ndimage import correlate

        return np.asarray(correlate(image.astype(np.float32), kernel, mode="mirror"))

    def jpeg_bytes(self, image: np.ndarray, scale: float, quality: int) -> int:
        raise ValueError(
            "the jpeg_size metric encodes JPEG with OpenCV, which is not installed: "
            "install focustrack-focus[service] (or opencv-python-headless), or pick another metric"
        )


def _binomial_half(image: np.ndarray) -> np.ndarray:
    """The unnormalised binomial taps (1 4 6 4 1) down axis 0, at every second row, of
    (h, w) -> ((h + 1) // 2, w); reflect-101 borders (numpy's `reflect`)."""
    padded = np.pad(image, ((2, 2), (0, 0)), mode="reflect")
    outer = padded[0:-4:2] + padded[4::2]
    inner = padded[1:-3:2] + padded[3:-1:2]
    return outer + 4 * inner + 6 * padded[2:-2:2]


def _best_backend() -> Filters:
    """OpenCV's filters where `cv2` imports, else scipy's."""
    try:
        return OpenCVFilters(importlib.import_module("cv2"))
    except ImportError:  # not installed, or installed without its system libraries (libGL)
        return ScipyFilters()


#: The backend the focus maths uses (tests swap it to compare the two).
BACKEND: Filters = _best_backend()
