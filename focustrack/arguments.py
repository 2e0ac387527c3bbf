"""argparse types that check a command's arguments when it starts, and `refuse` for
arguments each valid but not together.

The benchmarks, the demo and `focus calibrate` run for minutes to hours and write their
outputs at the end: an output that cannot be written, or a count that admits no work
(`--seeds 0`, `--size 0`), is an argparse error at once (exit 2, one line), not a
traceback after the work or a value silently replaced.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path

from focustrack_core.settings import make_writable_folder


def _check_writable_folder(folder: Path, text: str) -> None:
    """ArgumentTypeError unless `folder` is, or can now be made, a folder this process
    writes into (the run would make it at its end)."""
    try:
        make_writable_folder(folder)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"cannot write {text}: {error}") from None


def output_file(text: str) -> Path:
    """A file the command writes: not a folder, and in a folder it can make and write to."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write {text}: it is a folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"cannot write {text}: it is not writable")
    _check_writable_folder(path.parent, text)
    return path


def output_folder(text: str) -> Path:
    """A folder the command writes into: one it can make (or has) and write to."""
    path = Path(text)
    _check_writable_folder(path, text)
    return path


def _whole_number(text: str) -> int:
    try:
        return int(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from error


def whole_number(low: int, high: int | None = None) -> Callable[[str], int]:
    """The argparse type of a whole number of at least `low` (a seed: 0, a side: 2) and,
    given `high`, at most `high` (where more would overflow or run for days)."""
    allowed = f"at least {low}" if high is None else f"in [{low}, {high}]"

    def parse(text: str) -> int:
        value = _whole_number(text)
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {value}")
        return value

    return parse


#: A whole number of at least 1 (frames, seeds, workers, repeats).
positive_int = whole_number(1)

#: The most repeats, runs, stacks or maps a benchmark takes: far more than a realistic
#: run, far fewer than one that would run for days or fill the memory.
MAX_COUNT = 10_000

#: A count of repeats, runs, stacks or maps: 1 to `MAX_COUNT`.
count_number = whole_number(1, MAX_COUNT)

#: A seed every numpy generator takes (the legacy `RandomState` wants one below 2**32).
seed_number = whole_number(0, 2**32 - 1)


def user_id(text: str) -> int:
    """A user id: a whole number of at least 0."""
    if (value := _whole_number(text)) < 0:
        raise argparse.ArgumentTypeError(f"a user id is at least 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number above 0 (seconds, scales)."""
    try:
        value = float(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from error
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def finite_number(
    low: float = -math.inf, high: float = math.inf, *, below_high: bool = False
) -> Callable[[str], float]:
    """The argparse type of a finite number in [`low`, `high`] (or [`low`, `high`) with
    `below_high`); the bounds in the flag's own unit."""
    if math.isinf(low) and math.isinf(high):
        allowed = "a finite number"
    elif math.isinf(high):
        allowed = f"a finite number >= {low:g}"
    else:
        allowed = f"a number in [{low:g}, {high:g}{')' if below_high else ']'}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        above_high = value >= high if below_high else value > high
        if not math.isfinite(value) or value < low or above_high:
            raise argparse.ArgumentTypeError(f"must be {allowed}, got {text}")
        return value

    return parse


def existing_folder(text: str) -> Path:
    """A folder the command reads: it must be there (a data folder given by hand that is
    not is a typo, not a reason to leave its rows out)."""
    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is not a folder")
    return path


def refuse(command: str, message: str) -> int:
    """Refuse arguments that are each valid but not together, as argparse refuses one: a
    line on stderr naming `command` (`bench focus`); the exit status 2 to return."""
    print(f"focustrack {command}: error: {message}", file=sys.stderr)
    return 2
