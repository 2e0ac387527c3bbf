"""The frames of recent stacks an instrument keeps for queries, within a memory budget."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.v1 import instrument_pb2
from focustrack_instrument_sim.recent import RecentStacks, StackGoneError

SHAPE = (4, 6, 3)
DTYPE = np.dtype(np.uint16)
FRAME_BYTES = int(np.prod(SHAPE)) * DTYPE.itemsize


def _stack(store: RecentStacks, sequence: int, n: int, row: int = 0) -> list[np.ndarray]:
    """Renders (fills with `sequence`) and keeps a stack of `n` frames; its frames."""
    header = instrument_pb2.ZStackHeader(slide="s", row=row, col=1, sequence=sequence)
    frames = []
    for index in range(n):
        frame = store.buffer(SHAPE, DTYPE)
        frame[...] = 100 * sequence + index
        frames.append(frame)
    store.keep(header, frames, recyclable=True)
    return frames


def test_the_oldest_stacks_go_once_the_budget_is_spent_and_the_newest_always_stays() -> None:
    store = RecentStacks(budget_bytes=5 * FRAME_BYTES)
    for sequence in range(4):
        _stack(store, sequence, n=3)
    # Besides the newest (3 frames), 5 frames' worth: stack 2 only.
    assert store.copies("s", 0, 1, 0, []) is None
    assert store.copies("s", 0, 1, 1, []) is None
    header, [(index, frame)] = store.copies("s", 0, 1, 2, [2])
    assert header.sequence == 2 and index == 2 and int(frame[0, 0, 0]) == 202
    assert store.copies("s", 0, 1, 3, []) is not None
    tiny = RecentStacks(budget_bytes=0)
    _stack(tiny, 7, n=10)  # larger than the budget, and the newest: kept
    assert len(list(tiny.copies("s", 0, 1, 7, [])[1])) == 10


def test_copies_are_the_frames_asked_for_and_outlive_the_reuse_of_their_buffers() -> None:
    store = RecentStacks(budget_bytes=0)
    _stack(store, 1, n=3)
    _, [(i, second), (j, first)] = store.copies("s", 0, 1, 1, [2, 0])
    assert (i, j) == (2, 0)
    assert int(second[0, 0, 0]) == 102 and int(first[0, 0, 0]) == 100
    assert second.shape == SHAPE and second.dtype == DTYPE
    _stack(store, 2, n=3)  # renders into stack 1's buffers
    assert int(second[0, 0, 0]) == 102  # the copy is the frame as it was
    with pytest.raises(IndexError, match="frame 3 of a stack of 3 frames"):
        store.copies("s", 0, 1, 2, [3])
    assert store.copies("s", 5, 1, 2, []) is None  # another tile


def test_each_frame_asked_for_is_copied_once_as_it_is_drawn() -> None:
    store = RecentStacks(budget_bytes=0)
    _stack(store, 1, n=3)
    _, frames = store.copies("s", 0, 1, 1, [2] * 2000 + [0, 2])
    index, frame = next(frames)  # one copy made, whatever the request asks
    assert index == 2 and int(frame[0, 0, 0]) == 102
    assert [index for index, _ in frames] == [0]
    with pytest.raises(IndexError, match="frame 3"):  # refused before any copy
        store.copies("s", 0, 1, 1, [0, 3])
    _, frames = store.copies("s", 0, 1, 1, [])
    assert next(frames)[0] == 0
    _stack(store, 2, n=3)  # stack 1 dropped, its buffers rendered into again
    with pytest.raises(StackGoneError, match="stack 1 was dropped"):
        next(frames)


def test_dropped_stacks_buffers_are_rendered_into_again() -> None:
    store = RecentStacks(budget_bytes=0)
    first = _stack(store, 1, n=3)
    second = _stack(store, 2, n=3)
    third = _stack(store, 3, n=3)
    assert {id(frame) for frame in third} == {id(frame) for frame in first}
    assert not {id(frame) for frame in second} & {id(frame) for frame in third}


def test_a_stack_taken_again_replaces_the_earlier_one() -> None:
    store = RecentStacks(budget_bytes=100 * FRAME_BYTES)
    _stack(store, 4, n=2)
    header = instrument_pb2.ZStackHeader(slide="s", row=0, col=1, sequence=4, clock_s=9.0)
    store.keep(header, [np.full(SHAPE, 7, DTYPE)], recyclable=False)
    kept_header, [(index, frame)] = store.copies("s", 0, 1, 4, [])
    assert kept_header.clock_s == 9.0 and index == 0 and int(frame[0, 0, 0]) == 7


def test_a_negative_budget_is_refused() -> None:
    with pytest.raises(ValueError, match="must not be negative"):
        RecentStacks(budget_bytes=-1)
