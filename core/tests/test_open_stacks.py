"""The stacks a frame reader has under way: their bytes, their expiry, the failed ones."""

from __future__ import annotations

from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire.open_stacks import FAILED_STACKS, OpenStacks, stack_id


class Clock:
    """A clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_stacks_are_counted_expire_oldest_first_and_failed_ones_are_remembered() -> None:
    clock = Clock()
    stacks: OpenStacks[str] = OpenStacks(clock)
    header = instrument_pb2.ZStackHeader(sequence=3, clock_s=1.5, nonce=b"n")
    a, b = stack_id("k/a", header), stack_id("k/b", header)
    assert a == ("k/a", 3, 1.5, b"n")
    stacks.put(a, "first", 100)
    clock.now_s = 5.0
    stacks.put(b, "second", 50)
    stacks.put(a, "first again", 120)  # fed again: now the newest, its bytes replaced
    assert stacks.held_bytes == 170
    clock.now_s = 14.0
    assert stacks.expired(10.0) == []
    clock.now_s = 15.5
    assert stacks.expired(10.0) == [(b, "second"), (a, "first again")]
    assert stacks.held_bytes == 0 and stacks.pop(a) is None
    stacks.put(a, "third", 10)
    stacks.fail(a)  # no longer under way, and remembered
    assert stacks.failed(a) and stacks.held_bytes == 0
    for sequence in range(FAILED_STACKS):
        stacks.fail(("k/c", sequence, 0.0, b""))
    assert not stacks.failed(a)  # the oldest failure is forgotten
