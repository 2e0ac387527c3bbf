"""argparse types that check a command's arguments when it starts.

The benchmarks, the demo and `focus calibrate` run for minutes to hours and write their
outputs at the end: an output that cannot be written, or a count that admits no work
(`--seeds 0`, `--size 0`), is an argparse error at once (exit 2, one line), not a
traceback after the work or a value silently replaced.
"""

from __future__ import annotations

import argparse
import math
import os
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


def positive_int(text: str) -> int:
    """A whole number of at least 1 (frames, seeds, workers, repeats)."""
    if (value := _whole_number(text)) < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


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
