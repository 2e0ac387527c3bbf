"""The frames of the stacks an instrument acquired lately, within a memory budget.

Only the focus service needs every frame; the scheduler keeps one frame of a tile, or
its few planes, and knows which only once the tile's focus is known. So the instrument
keeps each stack's frames as they were rendered, and answers queries for them
(``focustrack/v1/instrument/{name}/frames``): a frame then crosses Zenoh once to be
measured and once more only when it is kept. Like a camera's circular buffer, the
oldest stacks go first once the budget is spent, and their buffers are rendered into
again (no fresh megabytes, and their page faults, per frame).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import codec

#: A stack's identity: slide, row, col and the sequence of its AcquireRequest.
StackId = tuple[str, int, int, int]


@dataclass(frozen=True)
class KeptStack:
    """A stack's header and its frames (height, width, channels), in z order."""

    header: instrument_pb2.ZStackHeader
    frames: tuple[np.ndarray, ...]
    recyclable: bool  # the frames are buffers of their own (`RecentStacks.buffer`)

    @property
    def nbytes(self) -> int:
        return sum(frame.nbytes for frame in self.frames)


def _copy(frame: np.ndarray) -> np.ndarray:
    """A copy of `frame` in a buffer of its own (Zenoh sends it without another copy)."""
    copy = codec.pixel_array(frame.shape, frame.dtype)
    copy[...] = frame
    return copy


class StackGoneError(LookupError):
    """A stack was dropped (its buffers to be rendered into again) while its frames were read."""


def stack_id(header: instrument_pb2.ZStackHeader) -> StackId:
    return header.slide, header.row, header.col, header.sequence


class RecentStacks:
    """The last stacks' frames, at most `budget_bytes` of them besides the newest stack
    (always kept, however large); thread-safe.

    Memory: the budget, the newest stack, and spare buffers for one more stack like it
    (dropped stacks' buffers, which `buffer` hands out again). A stack taken again with
    the same sequence replaces the earlier one.
    """

    def __init__(self, budget_bytes: int) -> None:
        if budget_bytes < 0:
            raise ValueError(f"the frame budget must not be negative, got {budget_bytes} bytes")
        self.budget_bytes = budget_bytes
        self._stacks: OrderedDict[StackId, KeptStack] = OrderedDict()
        self._free: list[np.ndarray] = []  # buffers of dropped stacks, to render into again
        self._lock = threading.Lock()

    def buffer(self, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """An array of `shape` and `dtype` to render a frame into: a dropped stack's buffer
        where one fits, else a new one (`codec.pixel_array`: Zenoh sends it without a copy)."""
        with self._lock:
            while self._free:
                candidate = self._free.pop()
                if candidate.shape == shape and candidate.dtype == dtype:
                    return candidate
        return codec.pixel_array(shape, dtype)

    def keep(
        self,
        header: instrument_pb2.ZStackHeader,
        frames: list[np.ndarray],
        *,
        recyclable: bool,
    ) -> None:
        """Keep a stack's frames; `recyclable` when they came from `buffer`. Drops the
        oldest stacks while the others exceed the budget."""
        kept = KeptStack(header, tuple(frames), recyclable)
        with self._lock:
            self._release(self._stacks.pop(stack_id(header), None))
            self._stacks[stack_id(header)] = kept
            held = sum(stack.nbytes for stack in self._stacks.values())
            while len(self._stacks) > 1 and held - kept.nbytes > self.budget_bytes:
                _, dropped = self._stacks.popitem(last=False)
                held -= dropped.nbytes
                self._release(dropped)
            # Spare buffers for one more stack like this one: the next renders into them.
            del self._free[: max(0, len(self._free) - len(kept.frames))]

    def copies(
        self, slide: str, row: int, col: int, sequence: int, indices: list[int]
    ) -> tuple[instrument_pb2.ZStackHeader, Iterator[tuple[int, np.ndarray]]] | None:
        """The header of that tile's stack of that sequence and its frames at `indices`
        (each once, in the order first asked; every frame when empty), or None when it is
        no longer kept. IndexError names a frame the stack does not have, before any frame
        is copied.

        The frames are (index, copy of the frame), each copied as it is drawn: a caller
        that sends each before drawing the next holds one frame at a time, however many
        a request names. Copies, because a dropped stack's buffers are rendered into
        again; StackGoneError when the stack is dropped before all are drawn.
        """
        with self._lock:
            stack = self._stacks.get((slide, row, col, sequence))
            if stack is None:
                return None
            n = len(stack.frames)
            wanted = list(dict.fromkeys(indices)) or list(range(n))
            for index in wanted:
                if not 0 <= index < n:
                    raise IndexError(f"frame {index} of a stack of {n} frames")
            header = instrument_pb2.ZStackHeader()
            header.CopyFrom(stack.header)
        return header, self._copies(stack, wanted)

    def _copies(self, stack: KeptStack, indices: list[int]) -> Iterator[tuple[int, np.ndarray]]:
        for index in indices:
            with self._lock:
                if self._stacks.get(stack_id(stack.header)) is not stack:
                    raise StackGoneError(
                        f"stack {stack.header.sequence} was dropped while its frames were sent"
                    )
                copy = _copy(stack.frames[index])
            yield index, copy

    def _release(self, stack: KeptStack | None) -> None:
        if stack is not None and stack.recyclable:
            self._free.extend(stack.frames)
