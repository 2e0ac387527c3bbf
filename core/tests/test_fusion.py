"""Extended depth of field: each part of the fused image comes from the frame sharp there."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.fusion import box_sum, fuse_planes


def _blurred(image: np.ndarray, passes: int) -> np.ndarray:
    """A crude defocus: `passes` 3x3 box blurs."""
    for _ in range(passes):
        image = box_sum(image, 3) / 9.0
    return image


def test_a_box_sum_is_the_window_sum_with_edges_replicated() -> None:
    image = np.arange(20.0).reshape(4, 5)
    padded = np.pad(image, 1, mode="edge")
    expected = np.array([[padded[r : r + 3, c : c + 3].sum() for c in range(5)] for r in range(4)])
    np.testing.assert_allclose(box_sum(image, 3), expected)


def test_each_half_of_the_fused_tile_comes_from_the_frame_in_focus_there() -> None:
    rng = np.random.default_rng(1)
    texture = rng.uniform(0, 4000, (64, 64))
    sharp_left = np.hstack([texture[:, :32], _blurred(texture, 6)[:, 32:]])
    sharp_right = np.hstack([_blurred(texture, 6)[:, :32], texture[:, 32:]])
    frames = np.stack([sharp_left, _blurred(texture, 6), sharp_right]).astype(np.uint16)
    fused = fuse_planes(frames)
    assert fused.dtype == np.uint16 and fused.shape == (64, 64)
    # away from the seam (the window straddles it), each side is the sharp frame's pixels
    np.testing.assert_array_equal(fused[:, :26], frames[0][:, :26])
    np.testing.assert_array_equal(fused[:, 38:], frames[2][:, 38:])


def test_colour_frames_keep_their_channels_together() -> None:
    rng = np.random.default_rng(2)
    texture = rng.uniform(0, 4000, (32, 32, 3))
    soft = np.stack([_blurred(texture[..., c], 4) for c in range(3)], axis=2)
    fused = fuse_planes(np.stack([soft, texture]).astype(np.uint16))
    np.testing.assert_array_equal(fused[4:-4, 4:-4], texture.astype(np.uint16)[4:-4, 4:-4])
    with pytest.raises(ValueError, match="frames must be"):
        fuse_planes(np.zeros((0, 4, 4)))
