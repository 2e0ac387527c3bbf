"""The stacks a frame reader has under way: what each holds, when its last frame came, and the
stacks it answered with an error (whose later frames it ignores).

The focus service (a focus curve per stack) and the phase service (a stack's counts) read
the frames of z-stacks as they come; both keep, per stack under way, what it holds so
far, told apart by `stack_id`. `OpenStacks` keeps them, the one fed longest ago first, with
their bytes counted (against the reader's budget) and their last frame's time (for
`expired`), and the last `FAILED_STACKS` stacks that ended in an error.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from focustrack_core.v1 import instrument_pb2

#: Stacks answered with an error that are remembered, whose later frames are ignored.
FAILED_STACKS = 64

#: A stack: the key of its frames, its sequence number, its simulated clock and the nonce
#: of its acquisition (an acquisition taken again keeps its sequence).
StackId = tuple[str, int, float, bytes]

V = TypeVar("V")


def stack_id(key: str, header: instrument_pb2.ZStackHeader) -> StackId:
    """The stack of a frame on `key` whose header's stack is `header`."""
    return (key, header.sequence, header.clock_s, header.nonce)


@dataclass
class _UnderWay(Generic[V]):
    value: V
    held_bytes: int
    last_s: float  # when its last frame came, by the clock, s


class OpenStacks(Generic[V]):
    """Stacks under way, each a value `V` holding `held_bytes`; see the module docstring."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._open: OrderedDict[StackId, _UnderWay[V]] = OrderedDict()
        self._held_bytes = 0
        self._failed: OrderedDict[StackId, None] = OrderedDict()

    @property
    def held_bytes(self) -> int:
        """What the stacks under way hold together, bytes."""
        return self._held_bytes

    def put(self, stack: StackId, value: V, held_bytes: int) -> None:
        """`stack` is under way with `value`, holding `held_bytes`; its frame came now."""
        self.pop(stack)
        self._open[stack] = _UnderWay(value, held_bytes, self.clock())
        self._held_bytes += held_bytes

    def pop(self, stack: StackId) -> V | None:
        """Take `stack` out of those under way (its bytes off the count); its value, if any."""
        under_way = self._open.pop(stack, None)
        if under_way is None:
            return None
        self._held_bytes -= under_way.held_bytes
        return under_way.value

    def expired(self, timeout_s: float) -> list[tuple[StackId, V]]:
        """Take out (and give back) the stacks whose last frame came over `timeout_s` ago."""
        deadline_s = self.clock() - timeout_s
        expired = []
        while self._open:
            stack, oldest = next(iter(self._open.items()))
            if oldest.last_s >= deadline_s:
                break
            self.pop(stack)
            expired.append((stack, oldest.value))
        return expired

    def fail(self, stack: StackId) -> None:
        """`stack` ended in an error: no longer under way, and its later frames are ignored."""
        self.pop(stack)
        self._failed[stack] = None
        while len(self._failed) > FAILED_STACKS:
            self._failed.popitem(last=False)

    def failed(self, stack: StackId) -> bool:
        """True when `stack` ended in an error (one of the last `FAILED_STACKS`)."""
        return stack in self._failed
