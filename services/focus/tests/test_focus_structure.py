"""The structure test: pixel noise read from a frame, and fields with nothing to focus on."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.pipeline import FocusSettings, focus_stack
from focustrack_focus.preprocess import Preprocess
from focustrack_focus.structure import (
    lowpass_noise_gain,
    pixel_noise_std,
    structure_snr,
)

PREPROCESS = Preprocess(lowpass_sigma_px=1.6)


@pytest.mark.parametrize("noise_std", [0.5, 3.0, 20.0])
def test_pixel_noise_is_read_from_a_textured_frame(noise_std: float) -> None:
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:300, 0:300]
    smooth = 1000.0 + 200.0 * np.sin(x / 15.0) * np.cos(y / 21.0)  # content, not noise
    frame = smooth + rng.normal(0.0, noise_std, smooth.shape)
    assert pixel_noise_std(frame) == pytest.approx(noise_std, rel=0.1)
    assert pixel_noise_std(smooth) < 0.05 * max(noise_std, 1.0)


def test_lowpass_gain_is_that_of_a_gaussian() -> None:
    # white noise through a Gaussian of sigma s keeps 1 / (4 pi s**2) of its variance
    gain = lowpass_noise_gain((512, 512), 3.0, Preprocess(lowpass_sigma_px=3.0).pyramid_levels)
    assert gain == pytest.approx(1.0 / (4.0 * math.pi * 9.0), rel=0.25)


def snr_of(frames: np.ndarray) -> float:
    """structure_snr between the first and the last frame of (n, H, W) frames, as the pipeline
    would call it with the first as the sharpest."""
    sharp, blurred = PREPROCESS(frames[0]), PREPROCESS(frames[-1])
    return structure_snr(sharp, blurred, PREPROCESS.crop(frames[-1]), PREPROCESS)


@pytest.mark.parametrize("size_px", [64, 128, 256])
def test_pure_noise_stays_far_below_the_threshold(size_px: int) -> None:
    rng = np.random.default_rng(size_px)
    snrs = [snr_of(rng.normal(2000.0, 20.0, (2, size_px, size_px))) for _ in range(40)]
    assert max(np.abs(snrs)) < 5.0, snrs  # the service's threshold is 10


def test_a_field_with_cells_stands_far_above_it(render: Callable[..., np.ndarray]) -> None:
    frames = render(128, np.array([0.0, 3.0]), 0.0, 2)
    assert snr_of(frames) > 100.0


def test_static_structure_cancels_and_noise_free_frames_cannot_be_judged() -> None:
    rng = np.random.default_rng(4)
    shading = np.linspace(500.0, 3000.0, 128)[None, :] * np.ones((128, 1))  # uneven light
    frames = shading + rng.normal(0.0, 15.0, (2, 128, 128))
    assert snr_of(frames) < 5.0
    assert snr_of(np.stack([shading, shading + 1.0])) == math.inf


@pytest.mark.parametrize("level", [0, 7])
def test_uniform_frames_are_flat_and_empty(level: int) -> None:
    """An all-black stack (exposure 0) read `flat` alone: with no pixel noise the structure
    test could not judge it, though nothing is in view."""
    z_um = np.arange(41) * 0.5 - 10.0
    frames = np.full((41, 64, 64), level, np.uint16)
    assert focus_stack(frames, z_um, FocusSettings()).flags == {FocusFlag.FLAT, FocusFlag.EMPTY}
