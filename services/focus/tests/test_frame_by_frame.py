"""Frame-by-frame focus gives what `focus_stack` gives for the whole stack, a look and the
rest of its stack included."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_focus.pipeline import (
    FocusSettings,
    FrameByFrame,
    LastLooks,
    continues,
    focus_stack,
)


def _stack(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 9-frame (9, 64, 64) uint16 stack whose texture is sharpest at z = 0.5 um."""
    rng = np.random.default_rng(seed)
    texture = rng.random((64, 64))
    z_um = np.arange(-2.0, 2.01, 0.5)
    frames = []
    for z in z_um:
        weight = np.exp(-((z - 0.5) ** 2))
        frames.append(1000 + 800 * (weight * texture + (1 - weight) * texture.mean()))
    noisy = np.asarray(frames) + rng.normal(0, 2, (len(z_um), 64, 64))
    return np.clip(noisy, 0, 4095).astype(np.uint16), z_um


def test_frames_in_any_order_give_the_whole_stack_result() -> None:
    frames, z_um = _stack()
    settings = FocusSettings()
    whole = focus_stack(frames, z_um, settings)
    incremental = FrameByFrame(z_um, settings)
    for index in np.random.default_rng(1).permutation(len(z_um)):
        assert not incremental.complete
        incremental.add(int(index), frames[index])
    assert incremental.complete
    result = incremental.result()
    np.testing.assert_allclose(result.scores, whole.scores)
    assert result.best_z_um == pytest.approx(whole.best_z_um)
    assert result.sigma_um == pytest.approx(whole.sigma_um)
    assert result.flags == whole.flags and result.best_z_um == pytest.approx(0.5, abs=0.15)
    assert result.compute_time_s > 0


def test_frames_that_are_not_intensities_are_refused_on_both_paths() -> None:
    """A background-subtracted frame, whose mean the metrics divide by, is refused by name;
    a black frame (no light) is one of intensities."""
    frames, z_um = _stack()
    signed = frames.astype(np.float32)
    signed[3] -= 2.0 * signed[3].mean()
    needle = r"frame 3 has a mean intensity of -1\d{3}(\.\d+)?: .* intensities \(raw counts\)"
    with pytest.raises(ValueError, match=needle):
        focus_stack(signed, z_um, FocusSettings())
    incremental = FrameByFrame(z_um, FocusSettings())
    incremental.add(2, signed[2])
    with pytest.raises(ValueError, match=needle):
        incremental.add(3, signed[3])
    incremental.add(4, np.zeros_like(signed[4]))


def test_missing_repeated_and_bad_frames_are_refused() -> None:
    frames, z_um = _stack()
    incremental = FrameByFrame(z_um, FocusSettings())
    incremental.add(0, frames[0])
    with pytest.raises(ValueError, match="arrived twice"):
        incremental.add(0, frames[0])
    with pytest.raises(ValueError, match="frame 9 of a stack of 9"):
        incremental.add(9, frames[0])
    with pytest.raises(ValueError, match="finite"):
        incremental.add(1, np.full((64, 64), np.nan))
    with pytest.raises(ValueError, match=r"frame 1 is \(32, 128\); the stack's first was"):
        incremental.add(1, frames[1].reshape(32, 128))  # the same pixels, another field
    huge = np.random.default_rng(0).uniform(1e307, 1.7e308, (64, 64))  # finite, past float32
    with (
        pytest.raises(ValueError, match=r"frame 1 scores nan .* overflow"),
        np.errstate(all="ignore"),
    ):
        incremental.add(1, huge)  # its NaN score read as "still to come": no result, ever
    with pytest.raises(ValueError, match="have not arrived"):
        incremental.result()
    with pytest.raises(ValueError):
        FrameByFrame(np.array([0.0, 1.0]), FocusSettings())  # too few frames for a curve


def test_a_look_continued_by_the_rest_of_its_stack_reads_as_the_whole_stack() -> None:
    frames, z_um = _stack()
    settings = FocusSettings()
    whole = focus_stack(frames, z_um, settings)
    look = FrameByFrame(z_um[:1], settings)
    look.add(0, frames[0])
    assert look.result().best_z_um is None  # a look: something in view, no focus
    joined = look.continued(z_um[1:])
    for index in range(1, len(z_um)):
        joined.add(index, frames[index])
    result = joined.result()
    np.testing.assert_allclose(result.scores, whole.scores)
    assert result.best_z_um == pytest.approx(whole.best_z_um)
    assert result.flags == whole.flags
    with pytest.raises(ValueError, match="do not continue"):
        look.continued(z_um[2:])  # a frame is missing between them


def test_continues_needs_the_rest_one_step_above_the_look_and_evenly_stepped() -> None:
    assert continues(0.0, np.array([0.5, 1.0]))
    assert not continues(0.0, np.array([1.0, 1.5]))  # a gap
    assert not continues(0.0, np.array([-1.0, -0.5]))  # below it
    assert not continues(0.0, np.array([0.5]))  # no step to compare
    assert not continues(0.0, np.array([0.5, 1.5]))  # uneven


def test_a_slides_last_look_joins_only_the_next_stack_of_its_tile() -> None:
    frames, z_um = _stack()
    settings = FocusSettings()
    looks = LastLooks(slides=1)
    look = FrameByFrame(z_um[:1], settings)
    look.add(0, frames[0])
    looks.keep("s1", (2, 3), look)
    assert looks.held_bytes == look.held_bytes > 0
    elsewhere = looks.curve("s1", (2, 4), z_um[1:], settings)  # another tile: its own curve
    assert elsewhere.z_um.size == len(z_um) - 1 and looks.held_bytes == 0
    looks.keep("s1", (2, 3), look)
    looks.keep("s2", (0, 0), look)  # one slide's looks at most: s1's is let go
    assert looks.curve("s1", (2, 3), z_um[1:], settings).z_um.size == len(z_um) - 1
    joined = looks.curve("s2", (0, 0), z_um[1:], settings)
    assert joined.z_um.size == len(z_um) and not joined.complete
