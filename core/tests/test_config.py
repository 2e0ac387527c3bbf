"""Every option of a command has an environment twin; the command line still wins."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from focustrack_core.config import with_environment


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, default=8100)
    p.add_argument("--store", default="estimator.sqlite")
    p.add_argument("--connect", nargs="*", default=[])
    p.add_argument("--metric", choices=["variance", "tenengrad"], default="variance")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--out", type=Path, default=Path("out"))
    return p


def test_the_environment_sets_defaults_and_flags_win() -> None:
    environ = {
        "APP_PORT": "9000", "APP_CONNECT": "tcp/a:1, tcp/b:2", "APP_NO_PROGRESS": "yes",
        "APP_OUT": "/out/x", "OTHER_PORT": "1",
    }  # fmt: skip
    args = with_environment(parser(), "APP_", environ).parse_args([])
    assert args.port == 9000 and args.connect == ["tcp/a:1", "tcp/b:2"]
    assert args.no_progress is True and args.out == Path("/out/x")
    assert args.store == "estimator.sqlite"  # unset: the flag's own default
    assert with_environment(parser(), "APP_", environ).parse_args(["--port", "7"]).port == 7
    assert "APP_PORT" in with_environment(parser(), "APP_", {}).format_help()


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("APP_PORT", "eighty", "APP_PORT='eighty'"),
        ("APP_METRIC", "brenner", "choose from variance, tenengrad"),
        ("APP_NO_PROGRESS", "maybe", "expected one of"),
    ],
)
def test_a_bad_value_is_a_clear_error(
    name: str, value: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        with_environment(parser(), "APP_", {name: value})
    assert message in capsys.readouterr().err
