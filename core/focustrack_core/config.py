"""Configuration from flags and the environment alike: every option has an environment twin.

A service's command-line options are its configuration. `with_environment`
gives each option of a parser the default ``{PREFIX}{DEST}`` from the
environment (``--store`` of the estimator: ``FOCUSTRACK_ESTIMATOR_STORE``), so
a container sets variables and runs the command as it is, with no shell to turn
variables into flags. A flag on the command line still wins. Values are parsed
and checked exactly as the flag's would be (its type and choices); a switch
(``store_true``) reads 1/true/yes/on and 0/false/no/off; a list option reads
its items separated by commas or spaces. `--help` names each variable.
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Callable, Mapping

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off", ""}


def variable(prefix: str, action: argparse.Action) -> str:
    """The environment variable of an option: ``{prefix}{DEST}``, e.g. FOCUSTRACK_FOCUS_PORT."""
    return f"{prefix}{action.dest.upper()}"


def with_environment(
    parser: argparse.ArgumentParser, prefix: str, environ: Mapping[str, str] | None = None
) -> argparse.ArgumentParser:
    """Let the environment set the defaults of `parser`'s options; returns `parser`."""
    environ = os.environ if environ is None else environ
    for action in parser._actions:  # argparse has no public list of its actions
        if not action.option_strings or action.dest in ("help", argparse.SUPPRESS):
            continue
        name = variable(prefix, action)
        action.help = f"{action.help or ''} [env {name}]".strip()
        if name in environ:
            action.default = _parse(parser, action, name, environ[name])
    return parser


def _parse(
    parser: argparse.ArgumentParser, action: argparse.Action, name: str, text: str
) -> object:
    if isinstance(action, argparse._StoreTrueAction | argparse._StoreFalseAction):
        word = text.strip().lower()
        if word not in _TRUE | _FALSE:
            parser.error(f"{name}={text!r}: expected one of 1/true/yes/on or 0/false/no/off")
        return (word in _TRUE) is isinstance(action, argparse._StoreTrueAction)
    convert = action.type if callable(action.type) else str
    many = action.nargs in ("*", "+") or isinstance(action.nargs, int)
    items = [item for item in re.split(r"[,\s]+", text.strip()) if item] if many else [text]
    values = []
    for item in items:
        try:
            value = convert(item)
        except (TypeError, ValueError) as error:
            parser.error(f"{name}={item!r}: {error}")
        if action.choices is not None and value not in action.choices:
            parser.error(f"{name}={item!r}: choose from {', '.join(map(str, action.choices))}")
        values.append(value)
    return values if many else values[0]


def command_main(
    prog: str,
    description: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    prefix: str,
) -> Callable[..., int]:
    """A console script's `main(argv=None)`: parse flags over the environment, then run."""

    def main(argv: list[str] | None = None) -> int:
        parser = argparse.ArgumentParser(prog=prog, description=description)
        add_arguments(parser)
        return run(with_environment(parser, prefix).parse_args(argv))

    return main
