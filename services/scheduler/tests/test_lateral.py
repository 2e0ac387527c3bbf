"""The second pass's lateral offset: bounded phase correlation of first- and second-pass tiles."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from focustrack_scheduler.lateral import MIN_SHARPNESS, pass_offset, phase_shift

SIDE = 128


def _texture(seed: int, shape: tuple[int, int] = (3 * SIDE, 6 * SIDE)) -> np.ndarray:
    return ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(shape), 2.0)


def _pairs(shift_px: tuple[float, float], n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    specimen = _texture(seed)
    moved = ndimage.shift(specimen, shift_px, order=3, mode="wrap")
    rng = np.random.default_rng(seed + 1)
    window = [np.s_[SIDE : 2 * SIDE, x : x + SIDE] for x in range(SIDE // 2, 5 * SIDE, SIDE)]
    return [
        (specimen[w] + 0.05 * rng.standard_normal((SIDE, SIDE)),
         moved[w] + 0.05 * rng.standard_normal((SIDE, SIDE)))
        for w in window[:n]
    ]  # fmt: skip


@pytest.mark.parametrize("shift_px", [(0.0, 0.0), (12.3, -20.6), (-30.5, 7.25)])
def test_a_shift_is_found_to_a_fraction_of_a_pixel(shift_px: tuple[float, float]) -> None:
    estimate = pass_offset(_pairs(shift_px, 4, seed=1), max_shift_px=40)
    assert estimate is not None
    assert estimate.dy_px == pytest.approx(shift_px[0], abs=0.3)
    assert estimate.dx_px == pytest.approx(shift_px[1], abs=0.3)


def test_the_search_is_bounded() -> None:
    first, second = _pairs((25.0, 0.0), 1, seed=2)[0]
    inside = phase_shift(first, second, max_shift_px=30)
    assert inside.dy_px == pytest.approx(25.0, abs=0.3)
    bounded = phase_shift(first, second, max_shift_px=10)  # the true peak is out of bounds
    assert abs(bounded.dy_px) <= 10.5 and abs(bounded.dx_px) <= 10.5
    assert bounded.sharpness < MIN_SHARPNESS <= inside.sharpness


def test_unrelated_or_flat_tiles_say_nothing() -> None:
    a, b = _texture(3)[:SIDE, :SIDE], _texture(4)[:SIDE, :SIDE]
    assert phase_shift(a, b, max_shift_px=40).sharpness < MIN_SHARPNESS
    flat = np.ones((SIDE, SIDE))
    assert pass_offset([(a, b), (flat, flat)], max_shift_px=40) is None
    with pytest.raises(ValueError, match="shape"):
        phase_shift(a, b[:, :-1], max_shift_px=5)
