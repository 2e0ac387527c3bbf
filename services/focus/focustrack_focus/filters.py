"""The image filters of the focus maths: OpenCV where it is installed, numpy and scipy otherwise.

OpenCV is an accelerator, not a dependency: the focus service installs it (extra
`service`), a lab's acquisition environment (`focustrack-lab`) need not. Both
backends give the same numbers (OpenCV's borders: reflect-101 is scipy's
`mirror`, OpenCV's `BORDER_REFLECT` scipy's `reflect`; `services/focus/tests/test_focus_filters.py`
checks them against each other). Measured per frame of the default pipeline
(docs/benchmarks.md): scipy's pyramid is 10 to 40 times slower than OpenCV's, so
the service keeps OpenCV. The one thing only OpenCV does is JPEG encoding (the
`jpeg_size` metric).
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType
from typing import Protocol

import numpy as np

#: The 5-tap binomial kernel of one pyramid level (OpenCV's pyrDown), variance 1 px**2.
_BINOMIAL = np.array([1, 4, 6, 4, 1], dtype=np.float32) / 16


class Filters(Protocol):
    """What the focus maths asks of an image library; images are 2-D, shapes (h, w)."""

    name: str

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

    def mean_std(self, image: np.ndarray) -> tuple[float, float]:
        return float(image.mean(dtype=np.float64)), float(image.std(dtype=np.float64))

    def pyr_down(self, image: np.ndarray) -> np.ndarray:
        from scipy.ndimage import correlate1d  # imported on first use, as the peak's scipy

        # Separable, so decimating the rows before filtering the columns gives the same
        # numbers at half the work; integer sums of at most 16 bits x 256 are exact in float32.
        rows = correlate1d(image.astype(np.float32), _BINOMIAL, axis=0, mode="mirror")[::2]
        out = correlate1d(rows, _BINOMIAL, axis=1, mode="mirror")[:, ::2]
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


def _best_backend() -> Filters:
    """OpenCV's filters where `cv2` imports, else scipy's."""
    if importlib.util.find_spec("cv2") is None:
        return ScipyFilters()
    return OpenCVFilters(importlib.import_module("cv2"))


#: The backend the focus maths uses (tests swap it to compare the two).
BACKEND: Filters = _best_backend()
