"""The second pass's lateral offset: bounded phase correlation of first- and second-pass tiles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from scipy import ndimage

from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.lateral import MIN_SHARPNESS, pass_offset, phase_shift
from focustrack_scheduler.ome_zarr import write_mosaic
from focustrack_scheduler.outputs import MOSAIC_ZARR, ZARR_ATTRS
from focustrack_scheduler.realign import FirstPassImages, LateralPlacement, Realign

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


def test_a_second_pass_finds_its_offset_against_the_first_pass_mosaic(tmp_path: Path) -> None:
    """`LateralPlacement` against a first pass's OME-Zarr mosaic (tiles side by side): a
    flat tile says nothing; once two tiles agree, the offset (x, y) um is known and every
    tile seen so far is handed back to be taken again."""
    grid = ScanGrid(2, 3)
    pixel_um = 0.1
    specimen = _texture(7, (2 * SIDE + 64, 3 * SIDE + 64))
    moved = ndimage.shift(specimen, (3.4, -6.2), order=3, mode="wrap")  # (y, x) px
    first = np.zeros((2 * SIDE, 3 * SIDE, 3), dtype=np.uint8)
    second = {}
    for row in range(2):
        for col in range(3):
            window = np.s_[
                32 + row * SIDE : 32 + (row + 1) * SIDE, 32 + col * SIDE : 32 + (col + 1) * SIDE
            ]
            first[row * SIDE : (row + 1) * SIDE, col * SIDE : (col + 1) * SIDE] = to_8_bits(
                specimen[window]
            )[..., None]
            second[(row, col)] = to_8_bits(moved[window])
    first[:SIDE, :SIDE] = 128  # tile (0, 0): empty glass
    path = tmp_path / MOSAIC_ZARR
    write_mosaic(path, first, pixel_um)
    zarr.open_group(path, mode="r+").attrs[ZARR_ATTRS] = {
        "tile_px": {"height": SIDE, "width": SIDE}
    }
    placement = LateralPlacement(FirstPassImages(tmp_path, grid), Realign(tmp_path, tiles=2))
    assert placement.observe(0, 0, 1.0, np.full((SIDE, SIDE), 128.0)) == []
    assert placement.observe(0, 1, 2.0, second[(0, 1)]) == []
    assert placement.offset_um is None
    again = placement.observe(0, 2, 3.0, second[(0, 2)])
    assert again == [(0, 0, 1.0), (0, 1, 2.0), (0, 2, 3.0)]
    assert placement.offset_um == pytest.approx((-0.62, 0.34), abs=0.02)
    assert placement.observe(1, 2, 4.0, second[(1, 2)]) == []  # known: nothing more to do


def to_8_bits(image: np.ndarray) -> np.ndarray:
    return np.clip(128 + 60 * image / image.std(), 0, 255).astype(np.uint8)


def test_a_first_pass_without_a_mosaic_is_refused_in_words(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        FirstPassImages(tmp_path, ScanGrid(2, 2))
    zarr.open_group(tmp_path / MOSAIC_ZARR, mode="w")  # a zarr, but no mosaic in it
    with pytest.raises(ValueError, match="not the mosaic of a FocusTrack scan"):
        FirstPassImages(tmp_path, ScanGrid(2, 2))
