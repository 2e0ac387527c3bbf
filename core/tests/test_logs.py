"""A repeated event is logged at its 1st, 2nd, 4th, 8th... occurrence."""

from focustrack_core.logs import worth_logging


def test_a_repeated_event_is_logged_ever_more_rarely() -> None:
    assert [count for count in range(1, 70) if worth_logging(count)] == [1, 2, 4, 8, 16, 32, 64]
    assert sum(worth_logging(count) for count in range(1, 1 << 20)) == 20
