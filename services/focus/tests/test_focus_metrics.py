"""Focus metrics and preprocessing: metrics prefer focus; the pyramid is the Gaussian it claims."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.metrics import DEFAULT_METRIC, METRICS, get_metric
from focustrack_focus.pipeline import FocusSettings, focus_stack
from focustrack_focus.preprocess import (
    Preprocess,
    lowpass,
    lowpass_sigma_for_optics,
    select_channel,
)


@pytest.fixture(scope="module")
def stack(render: Callable[..., np.ndarray]) -> np.ndarray:
    """Frames at defocus -2, 0, +2 um of a field of cells, (3, 128, 128) uint16."""
    return render(128, np.array([-2.0, 0.0, 2.0]), 0.0, 2)


@pytest.mark.parametrize("name", list(METRICS))
def test_every_metric_is_largest_in_focus(stack: np.ndarray, name: str) -> None:
    metric, preprocess = get_metric(name), Preprocess(lowpass_sigma_px=1.7)
    scores = [metric(preprocess(frame)) for frame in stack]
    assert scores[1] > scores[0] and scores[1] > scores[2], scores


def test_default_metric_is_normalised_variance_and_unknown_names_are_refused() -> None:
    assert DEFAULT_METRIC == "normalised_variance"
    with pytest.raises(ValueError, match="unknown focus metric 'nope'"):
        get_metric("nope")


@pytest.mark.parametrize("name", list(METRICS))
def test_every_metric_ignores_the_illumination_level(name: str) -> None:
    image = np.random.default_rng(2).uniform(50, 150, (64, 64)).astype(np.float32)
    metric = get_metric(name)
    # A contrast: a brighter (or dimmer) frame of the same field scores the same.
    tolerance = 0.02 if name == "jpeg_size" else 1e-4  # 8-bit rounding of the encoder
    assert metric(3 * image) == pytest.approx(metric(image), rel=tolerance)
    assert metric(0.5 * image) == pytest.approx(metric(image), rel=tolerance)


@pytest.mark.parametrize(("sigma_px", "levels"), [(0.0, 0), (0.9, 0), (1.0, 1), (2.0, 1), (2.3, 2)])
def test_pyramid_levels_stay_inside_the_requested_lowpass(sigma_px: float, levels: int) -> None:
    assert Preprocess(lowpass_sigma_px=sigma_px).pyramid_levels == levels


def test_pyramid_lowpass_removes_as_much_noise_as_the_full_gaussian() -> None:
    noise = np.random.default_rng(3).normal(0, 1, (512, 512)).astype(np.float32)
    sigma = 3.0
    pyramid = lowpass(noise, sigma, Preprocess(lowpass_sigma_px=sigma).pyramid_levels)
    full = cv2.GaussianBlur(noise, (0, 0), sigma)
    assert pyramid.shape == (128, 128)  # two pyrDowns
    # white noise variance after a Gaussian of sigma: 1 / (4 pi sigma**2)
    assert pyramid.var() == pytest.approx(full.var(), rel=0.25)
    assert full.var() == pytest.approx(1 / (4 * np.pi * sigma**2), rel=0.15)


def test_channel_choice_green_by_default_and_most_contrast_when_asked() -> None:
    rng = np.random.default_rng(4)
    frame = np.full((32, 32, 3), 100, np.uint8)
    frame[..., 2] = rng.integers(0, 255, (32, 32))  # only blue has contrast
    assert np.array_equal(select_channel(frame, 1), frame[..., 1])
    assert np.array_equal(select_channel(frame, None), frame[..., 2])
    with pytest.raises(ValueError, match="channel 5"):
        select_channel(frame, 5)
    # a monochrome camera's frame (the MMCore backend's "L"): its one channel, whichever
    # channel the settings name (green, by default)
    mono = frame[..., 2:]
    assert np.array_equal(select_channel(mono, 1), frame[..., 2])
    assert np.array_equal(select_channel(mono, None), frame[..., 2])


def test_roi_and_bad_settings() -> None:
    frame = np.arange(100 * 80, dtype=np.uint16).reshape(100, 80)
    out = Preprocess(roi=(10, 20, 40, 30), lowpass_sigma_px=0)(frame)
    assert out.shape == (40, 30) and out[0, 0] == frame[10, 20]
    with pytest.raises(ValueError, match="does not fit"):
        Preprocess(roi=(90, 0, 40, 30))(frame)
    with pytest.raises(ValueError, match="low-pass sigma"):
        Preprocess(lowpass_sigma_px=-1)


def test_lowpass_matched_to_the_optics() -> None:
    # thesis: 0.04 um pixels, NA 0.85, 0.70 um: PSF sigma 0.173 um = 4.3 px
    assert lowpass_sigma_for_optics(0.04, 0.85) == pytest.approx(0.21 * 0.70 / 0.85 / 0.04)


@pytest.mark.parametrize("metric", [name for name in METRICS if name != "jpeg_size"])
def test_a_stack_whose_brightness_alone_changes_with_z_is_flat(
    render: Callable[..., np.ndarray], metric: str
) -> None:
    # One field in focus, dimmed away from z = 0 (as Micro-Manager's demo camera does),
    # each frame with its own photon noise: nothing goes in or out of focus.
    z_um = np.linspace(-5.0, 5.0, 21)
    field = render(128, np.zeros(1), 0.0, 5)[0].astype(np.float64)
    rng = np.random.default_rng(6)
    gain = 1.0 / (1.0 + np.abs(z_um) / 2.0)
    stack = np.stack([rng.poisson(g * field) for g in gain]).astype(np.uint16)
    result = focus_stack(stack, z_um, FocusSettings(metric=metric))
    assert FocusFlag.FLAT in result.flags and result.best_z_um is None, result
