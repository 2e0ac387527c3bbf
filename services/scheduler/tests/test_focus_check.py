"""The second pass's first-frame check: sharpness and its ratio to the first pass's image."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from focustrack_scheduler.focus_check import (
    MIN_SHARPNESS_RATIO,
    out_of_focus,
    sharpness,
    sharpness_ratio,
)

SIDE = 96


def texture(seed: int = 3) -> np.ndarray:
    """A specimen: 1000 + band-limited detail, (SIDE + 40, SIDE + 40)."""
    noise = np.random.default_rng(seed).standard_normal((SIDE + 40, SIDE + 40))
    return 1000.0 + 200.0 * blurred(noise, 0.8)


def blurred(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """`image` convolved with a Gaussian of `sigma_px` (periodic): a defocus stand-in."""
    fy = np.fft.fftfreq(image.shape[0])[:, None]
    fx = np.fft.fftfreq(image.shape[1])[None, :]
    otf = np.exp(-2.0 * (np.pi * sigma_px) ** 2 * (fx**2 + fy**2))
    return np.fft.ifft2(np.fft.fft2(image) * otf).real


def test_sharpness_is_a_contrast_that_defocus_lowers() -> None:
    specimen = texture()
    assert sharpness(3.0 * specimen) == pytest.approx(sharpness(specimen))
    widths = [0.0, 0.5, 1.0, 2.0]
    values = [sharpness(blurred(specimen, w) if w else specimen) for w in widths]
    assert all(a > b for a, b in itertools.pairwise(values))
    assert sharpness(np.zeros((8, 8))) == 0.0  # a black frame: no detail, no error


def test_the_ratio_compares_the_part_both_show_after_the_shift() -> None:
    specimen = texture()
    reference = specimen[20 : 20 + SIDE, 20 : 20 + SIDE]
    # the second pass's frame shows the specimen 7 px further down and 5 px further left:
    # a feature at p of the reference lies at p + (7, -5) in it
    moved = specimen[13 : 13 + SIDE, 25 : 25 + SIDE]
    np.testing.assert_array_equal(moved[7:, :-5], reference[:-7, 5:])
    assert sharpness_ratio(moved, reference, (7, -5)) == pytest.approx(1.0)
    defocused = blurred(specimen, 1.0)[13 : 13 + SIDE, 25 : 25 + SIDE]
    ratio = sharpness_ratio(defocused, reference, (7, -5))
    assert ratio < MIN_SHARPNESS_RATIO and out_of_focus(ratio, MIN_SHARPNESS_RATIO)
    assert not out_of_focus(ratio, 0.0)  # 0: no check
    assert sharpness_ratio(reference, np.full_like(reference, 5.0), (0, 0)) == np.inf


def test_images_that_cannot_be_compared_are_refused() -> None:
    reference = texture()[:SIDE, :SIDE]
    with pytest.raises(ValueError, match="one shape"):
        sharpness_ratio(reference[:, :-2], reference, (0, 0))
    with pytest.raises(ValueError, match="too little"):
        sharpness_ratio(reference, reference, (SIDE - 8, 0))
