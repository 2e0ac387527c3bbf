"""Logging what a peer can make happen as often as it likes."""

from __future__ import annotations


def worth_logging(count: int) -> bool:
    """True for the 1st, 2nd, 4th, 8th... occurrence (`count` >= 1): a line for each of those
    keeps a repeated event visible, with its running count, without letting whoever causes
    it flood the log (40 lines for a trillion)."""
    return count & (count - 1) == 0
