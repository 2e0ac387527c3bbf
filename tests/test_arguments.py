"""Output paths on the command line are checked when a command starts (`focustrack.arguments`):
a long benchmark or demo used to run to its end and then fail writing, in a traceback."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

from focustrack.arguments import (
    output_file,
    output_folder,
    positive_float,
    positive_int,
    user_id,
)


def test_a_file_in_a_folder_that_can_be_made_is_taken_and_the_folder_made(
    tmp_path: Path,
) -> None:
    assert output_file(str(tmp_path / "new" / "out.json")) == tmp_path / "new" / "out.json"
    assert (tmp_path / "new").is_dir() and not (tmp_path / "new" / "out.json").exists()
    assert output_folder(str(tmp_path / "a" / "b")) == tmp_path / "a" / "b"


@pytest.mark.parametrize(
    ("kind", "where", "why"),
    [
        (output_file, "folder", "it is a folder"),
        (output_file, "file/out.json", "is not a folder"),
        (output_file, "/proc/no-such/out.json", "No such file or directory"),
        (output_folder, "file", "is not a folder"),
        (output_folder, "file/below", "is not a folder"),
    ],
)
def test_an_output_that_cannot_be_written_is_refused(
    tmp_path: Path, kind: object, where: str, why: str
) -> None:
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("taken")
    path = where if where.startswith("/") else str(tmp_path / where)
    with pytest.raises(argparse.ArgumentTypeError, match=why):
        kind(path)  # type: ignore[operator]


@pytest.mark.parametrize(
    "command",
    [
        ["bench", "accuracy", "--json", "/proc/no-such/out.json"],
        ["demo", "--json", "/proc/no-such/out.json"],
        ["focus", "calibrate", "--curves", "c.jsonl", "--out", "/proc/no-such/p.json"],
        ["bench", "tune", "--seeds", "0"],  # a traceback after the first phase
        ["bench", "focus", "--reps", "0"],  # ran with 4
        ["bench", "api", "--store", "mysql://db/x"],  # a traceback once the estimator refused
    ],
)
def test_a_command_with_an_output_it_cannot_write_stops_at_once(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    from focustrack import cli

    try:
        status = cli.main(command)
    except SystemExit as exit_:  # argparse's own refusals
        status = exit_.code
    stderr = capsys.readouterr().err
    assert status == 2, stderr
    assert "error: argument --" in stderr and "Traceback" not in stderr


@pytest.mark.parametrize("text", ["0", "-3", "1.5", "x"])
def test_a_count_below_one_is_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        positive_int(text)


@pytest.mark.parametrize("text", ["0", "-1", "inf", "nan", "x"])
def test_a_duration_that_is_not_above_zero_is_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        positive_float(text)


def test_counts_and_durations_above_zero_are_taken() -> None:
    assert positive_int("3") == 3 and positive_float("0.25") == 0.25


def test_a_user_id_is_a_whole_number_from_zero() -> None:
    """`bus secrets --owner -5` was a traceback after writing half its files."""
    assert user_id("0") == 0 and user_id("10001") == 10001
    for text in ("-5", "x", "1.5"):
        with pytest.raises(argparse.ArgumentTypeError):
            user_id(text)


def test_bench_instrument_with_an_odd_frame_side_stops_at_once(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from focustrack import cli

    assert cli.main(["bench", "instrument", "--size", "63"]) == 2  # it was a traceback
    assert "--size must be even, got 63" in capsys.readouterr().err


def test_bench_api_on_a_database_that_does_not_answer_says_so_in_one_line(tmp_path: Path) -> None:
    """The estimator starts (it serves 503 while its database is away); the bench's first
    request is refused after the estimator's store timeout (1 s here, from its variable),
    and the bench ends with the estimator's words, not a traceback."""
    done = subprocess.run(
        [sys.executable, "-m", "focustrack", "bench", "api", "--duration-s", "1",
         "--store", "postgresql://nobody@127.0.0.1:1/none"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
        env=os.environ | {"FOCUSTRACK_ESTIMATOR_STORE_TIMEOUT_S": "1"},
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "error: the estimator answered 503 to /v1/slides" in done.stderr, done.stderr
    assert "the estimator's store failed" in done.stderr and "Traceback" not in done.stderr
    assert "couldn't get a connection after 1.00 sec" in done.stderr
