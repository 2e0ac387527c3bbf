"""The two filter backends (OpenCV, numpy/scipy) give the same numbers, to float32 rounding."""

from __future__ import annotations

import sys
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from focustrack_focus import filters
from focustrack_focus.metrics import METRICS
from focustrack_focus.pipeline import FocusSettings, focus_stack

OPENCV = filters.OpenCVFilters(cv2)
SCIPY = filters.ScipyFilters()


def test_the_service_installs_opencv_and_uses_it() -> None:
    assert filters.BACKEND.name == "opencv"


def test_an_opencv_that_does_not_import_leaves_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    # None in sys.modules makes `import cv2` raise ImportError, as a wheel without its
    # system libraries (libGL) does.
    monkeypatch.setitem(sys.modules, "cv2", None)
    assert filters._best_backend().name == "scipy"


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("shape", [(64, 64), (37, 50), (5, 8)])
def test_pyramid_levels_are_equal(dtype: type, shape: tuple[int, int]) -> None:
    image = np.random.default_rng(1).integers(0, 250, shape).astype(dtype)
    expected = OPENCV.pyr_down(image)
    actual = SCIPY.pyr_down(image)
    assert actual.dtype == expected.dtype and actual.shape == expected.shape
    np.testing.assert_allclose(actual, expected, rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("sigma_px", [0.3, 0.866, 1.7])
def test_gaussian_blur_mean_std_and_correlation_are_equal(sigma_px: float) -> None:
    image = np.random.default_rng(2).uniform(0, 1000, (41, 64)).astype(np.float32)
    np.testing.assert_allclose(
        SCIPY.gaussian_blur(image, sigma_px), OPENCV.gaussian_blur(image, sigma_px), rtol=1e-5
    )
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    np.testing.assert_allclose(
        SCIPY.correlate(image, kernel), OPENCV.correlate(image, kernel), rtol=1e-5, atol=1e-2
    )
    np.testing.assert_allclose(SCIPY.mean_std(image), OPENCV.mean_std(image), rtol=1e-9)


@pytest.mark.parametrize("metric", [name for name in METRICS if name != "jpeg_size"])
def test_a_stack_reads_the_same_with_either_backend(
    render: Callable[..., np.ndarray], monkeypatch: pytest.MonkeyPatch, metric: str
) -> None:
    z_um = np.linspace(-3.0, 3.0, 13)
    stack = render(128, z_um, 0.4, 2)
    settings = FocusSettings(metric=metric)
    with_opencv = focus_stack(stack, z_um, settings)
    monkeypatch.setattr(filters, "BACKEND", SCIPY)
    with_scipy = focus_stack(stack, z_um, settings)
    np.testing.assert_allclose(with_scipy.scores, with_opencv.scores, rtol=1e-5)
    assert with_scipy.flags == with_opencv.flags
    assert with_opencv.best_z_um is not None and with_scipy.best_z_um is not None
    assert with_scipy.best_z_um == pytest.approx(with_opencv.best_z_um, abs=1e-4)


def test_jpeg_size_names_what_it_needs_without_opencv() -> None:
    with pytest.raises(ValueError, match="encodes JPEG with OpenCV, which is not installed"):
        SCIPY.jpeg_bytes(np.ones((8, 8), np.float32), 1.0, 90)
