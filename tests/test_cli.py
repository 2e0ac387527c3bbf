"""The `focustrack` command's own words: its usage, an unknown command, Ctrl-C early."""

from __future__ import annotations

import pytest

from focustrack import cli


def test_no_command_or_help_prints_the_usage(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in ([], ["--help"]):
        assert cli.main(argv) == 0
        assert capsys.readouterr().out.startswith("usage: focustrack COMMAND")


@pytest.mark.parametrize("argv", [["bench"], ["bench", "--help"], ["serve", "-h"]])
def test_a_group_of_commands_lists_its_own(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """`focustrack bench --help` said "unknown command 'bench'", status 2."""
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: focustrack {argv[0]} COMMAND")
    listed = [line.split()[0:2] for line in out.splitlines() if line.startswith("  ")]
    assert listed == [name.split() for name in cli.COMMANDS if name.startswith(f"{argv[0]} ")]


@pytest.mark.parametrize(
    ("argv", "named"), [(["bogus"], "'bogus'"), (["bench", "nope", "--x"], "'bench nope'")]
)
def test_an_unknown_command_is_named(
    argv: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """It used to print the usage alone, with status 2: nothing said what was wrong."""
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage:") and f"focustrack: error: unknown command {named}" in err


def test_ctrl_c_before_the_command_handles_it_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in a command's imports or parsing (its first second) was a traceback."""

    def interrupted(name: str) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.importlib, "import_module", interrupted)
    assert cli.main(["bench", "accuracy"]) == 130
    assert capsys.readouterr().err == "focustrack: interrupted\n"
