"""A service's settings from one model: its flags, its environment and an optional file.

Each service describes its options once, as a subclass of `ServiceSettings` (a
pydantic-settings model: a field per option, with its type, default, bounds and
help). From that one model come:

- the command line: ``--max-tile-seconds 0.2``, the field names in kebab case; a
  switch is ``--insecure`` (and ``--no-insecure``); a list takes its items after one
  flag (``--connect A B``), repeated flags, or commas;
- the environment: ``FOCUSTRACK_ESTIMATOR_MAX_TILE_SECONDS=0.2`` (the model's
  `env_prefix` and the field name in capitals), so a container sets variables and
  runs the command as it is; a list reads its items separated by commas or spaces;
- a settings file, ``--settings FILE`` (or ``{PREFIX}SETTINGS``): TOML or JSON, the
  field names as keys (``max_tile_seconds = 0.2``).

Precedence: a flag over the environment over the file over the model's default.
A value the model refuses stops the command with exit status 2 and a message
naming the option and what is wrong with it, as argparse does for a bad flag.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
import tomllib
from collections.abc import Callable, Iterable
from contextvars import ContextVar
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, ClassVar, Literal, Self, TypeVar, get_args, get_origin

from pydantic import AfterValidator, ValidationError, ValidationInfo, field_validator
from pydantic.fields import FieldInfo
from pydantic_settings import (
    BaseSettings,
    CliSettingsSource,
    InitSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

S = TypeVar("S", bound="ServiceSettings")

#: The option naming a settings file (besides its environment twin, ``{PREFIX}SETTINGS``).
SETTINGS_FILE_OPTION = "--settings"


class ServiceSettings(BaseSettings):
    """The base of every service's settings; subclasses set `env_prefix` in `model_config`."""

    model_config = SettingsConfigDict(
        extra="forbid",
        env_ignore_empty=True,  # an empty variable is an unset one (a switch stays off)
        cli_kebab_case=True,
        cli_implicit_flags=True,  # --insecure, not --insecure true
        cli_hide_none_type=True,
        validate_default=True,
        # No option means infinity or NaN: `--pitch-um inf`, `--z-offset-um nan` and
        # `--body-timeout-s inf` were taken, and broke the service later or silently.
        allow_inf_nan=False,
    )

    #: The heading of this model's own fields in `--help` (None: among the options).
    #: A model of options that others compose (the Zenoh options, a backend's) sets one.
    help_heading: ClassVar[str | None] = None

    #: Fields whose text (from the environment, a flag or a file) is a list of items
    #: separated by commas or spaces, as lists always read (set by subclasses).
    list_fields: ClassVar[tuple[str, ...]] = ()

    @field_validator("*", mode="before")
    @classmethod
    def _split_lists(cls, value: Any, info: ValidationInfo) -> Any:
        """A list field given as one text (environment, file) is its items."""
        if info.field_name in cls.list_fields and isinstance(value, str):
            return [item for item in re.split(r"[,\s]+", value.strip()) if item]
        return value

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        reading = _READING.get() or _Reading()
        if not reading.environment:
            return (init_settings,)
        sources: tuple[PydanticBaseSettingsSource, ...] = (init_settings, env_settings)
        if reading.file is not None:
            sources += (InitSettingsSource(settings_cls, read_settings_file(reading.file)),)
        return sources

    @classmethod
    def env_prefix(cls) -> str:
        return str(cls.model_config.get("env_prefix", ""))

    @classmethod
    def variable(cls, name: str) -> str:
        """The environment variable of field `name` (``FOCUSTRACK_FOCUS_PORT``)."""
        return f"{cls.env_prefix()}{name.upper()}"

    @classmethod
    def default_text(cls, name: str) -> str | None:
        """How `--help` states field `name`'s default, where the field's own value (None, say)
        stands for another (subclasses override); None: as the field's default reads."""
        return None

    @classmethod
    def add_arguments(cls, parser: argparse.ArgumentParser, *, environment: bool = True) -> None:
        """Add a flag for every field of the model to `parser`, and ``--settings`` where the
        settings also come from the environment and a file (`environment`)."""
        if environment:
            parser.add_argument(
                SETTINGS_FILE_OPTION,
                type=Path,
                metavar="FILE",
                dest="settings_file",
                help="a TOML or JSON file of settings by field name "
                f"[env {cls.variable('settings')}]",
            )
        add_argument = _add_argument(cls, environment)
        CliSettingsSource(cls, root_parser=parser, add_argument_method=add_argument)

    @classmethod
    def from_args(cls, args: argparse.Namespace, *, environment: bool = True) -> Self:
        """The settings of parsed flags over the environment, the file and the defaults
        (over the defaults alone without `environment`: a command whose options are only
        its flags, such as the demo's share of a scan's).

        Raises `SettingsError` naming each option the model refuses and why.
        """
        flags = vars(args).copy()
        file = flags.pop("settings_file", None)
        source: CliSettingsSource[Any] = CliSettingsSource(
            cls, root_parser=argparse.ArgumentParser(add_help=False)
        )
        parsed = source(parsed_args=argparse.Namespace(**flags))
        return cls.load(file, environment=environment, _cli_settings_source=parsed)

    @classmethod
    def load(cls, file: Path | None = None, *, environment: bool = True, **values: Any) -> Self:
        """The settings of `values` over the environment, the settings file (`file`, else the
        one ``{PREFIX}SETTINGS`` names, if any) and the defaults; over the defaults alone
        without `environment`. Raises `SettingsError` naming each option refused and why."""
        if file is None and environment:
            named = os.environ.get(cls.variable("settings"))
            file = Path(named) if named else None  # empty: unset, as every variable
        token = _READING.set(_Reading(file, environment))
        try:
            return cls(**values)
        except ValidationError as error:
            raise SettingsError(_describe(cls, error, _Reading(file, environment))) from None
        finally:
            _READING.reset(token)


@dataclass(frozen=True)
class _Reading:
    """Where `ServiceSettings.load` reads: a settings file, and whether the environment."""

    file: Path | None = None
    environment: bool = True


#: What the settings being built read (a context variable: builds on two threads at once
#: each read their own).
_READING: ContextVar[_Reading | None] = ContextVar("focustrack_settings_reading", default=None)


@dataclass(frozen=True)
class OneOf:
    """A text setting's choices, known at run time (a table's names): the validator of
    ``Annotated[str, AfterValidator(OneOf(names))]``, whose flag lists them as choices."""

    names: tuple[str, ...]

    def __call__(self, value: str) -> str:
        if value not in self.names:
            raise ValueError(f"{value!r} is not one of {', '.join(self.names)}")
        return value


def one_of(names: Iterable[str]) -> AfterValidator:
    """The metadata of a text setting that takes one of `names`:
    ``metric: Annotated[str, one_of(METRICS)]``."""
    return AfterValidator(OneOf(tuple(names)))


class SettingsError(ValueError):
    """Settings the model refuses (a bad value, an unreadable file); the message says which."""


def make_writable_folder(folder: Path) -> None:
    """Make `folder` (and its parents) unless it exists; ValueError saying why it cannot be
    a folder this process writes into: a file in its path, the system's refusal, no write
    permission. Only making it tells whether it can be (under /proc, say, even root
    cannot), so a command checks its output folder this way when it starts, not after
    its work."""
    existing = next((path for path in (folder, *folder.parents) if path.exists()), Path.cwd())
    if not existing.is_dir():
        raise ValueError(f"{existing} is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(error.strerror or str(error)) from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{folder} is not writable")


def read_settings_file(path: Path) -> dict[str, Any]:
    """The settings in a TOML (``.toml``, in any case) or JSON file, by field name;
    SettingsError if bad."""
    is_toml = path.suffix.lower() == ".toml"
    try:
        text = path.read_text()
        values = tomllib.loads(text) if is_toml else json.loads(text)
    except (OSError, ValueError) as error:
        hint = ""
        if not is_toml and path.suffix.lower() != ".json":  # a .yaml, a .ini
            hint = " (read as JSON: a TOML file's name ends in .toml)"
        raise SettingsError(f"settings file {path}: {error}{hint}") from None
    if not isinstance(values, dict):
        raise SettingsError(f"settings file {path}: expected a table of settings by name")
    return values


def _add_argument(cls: type[ServiceSettings], environment: bool) -> Callable[..., argparse.Action]:
    """The `add_argument` of CliSettingsSource, with today's list flags, env names in help,
    choices of Literal fields, and each field under the `help_heading` of the model
    declaring it."""
    groups: dict[type, Any] = {}

    def add_argument(parser: Any, *names: str, **kwargs: Any) -> argparse.Action:
        if kwargs.get("action") == "append":  # a list: its items after one flag, or repeated
            kwargs.update(action="extend", nargs="*")
            kwargs["metavar"] = re.sub(r"^list\[(.*)\]$", r"\1", str(kwargs.get("metavar", "")))
        dest = kwargs.get("dest", "")
        field = cls.model_fields.get(dest)
        if field is None:
            return parser.add_argument(*names, **kwargs)
        text = _help_text(cls, dest, field, str(kwargs.get("help", "")))
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        if "metavar" in extra:  # `Field(json_schema_extra={"metavar": "ENDPOINT"})`
            kwargs["metavar"] = extra["metavar"]
        elif kwargs.get("metavar") == "Path":
            kwargs["metavar"] = "FILE"
        kwargs["help"] = f"{text} [env {cls.variable(dest)}]".strip() if environment else text
        choices = _choices(field)
        if choices:
            kwargs["choices"] = choices
            kwargs.pop("metavar", None)
        owner = _declaring_model(cls, dest)
        heading = vars(owner).get("help_heading")
        if heading is not None:
            if owner not in groups:
                groups[owner] = parser.add_argument_group(heading)
            parser = groups[owner]
        return parser.add_argument(*names, **kwargs)

    return add_argument


def _help_text(cls: type[ServiceSettings], name: str, field: FieldInfo, text: str) -> str:
    """pydantic-settings' help of field `name` with its default as a user types it: an
    enum's value, the service's own words where the model says (`default_text`), nothing
    where it would say null or name a factory (the description says what unset means)."""
    stated = cls.default_text(name)
    if stated is None and isinstance(field.default, Enum):
        stated = str(field.default.value)
    if stated is not None:
        return re.sub(r"\(default: [^)]*\)", f"(default: {stated})", text)
    return re.sub(r" ?\(default(: null| factory: [^)]*)\)", "", text)


def _declaring_model(cls: type, name: str) -> type:
    """The class of `cls`'s hierarchy whose own annotations declare field `name`."""
    return next(
        (klass for klass in cls.__mro__ if name in vars(klass).get("__annotations__", {})), cls
    )


def _choices(field: FieldInfo) -> list[str] | None:
    """The values a Literal, enum or `one_of` field takes, as text (argparse lists them)."""
    annotation = field.annotation
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        return [str(member.value) for member in annotation]
    if get_origin(annotation) is Literal:
        return [str(value) for value in get_args(annotation)]
    for meta in field.metadata:
        if isinstance(meta, AfterValidator) and isinstance(meta.func, OneOf):
            return list(meta.func.names)
    return None


def _describe(cls: type[ServiceSettings], error: ValidationError, reading: _Reading) -> str:
    """One line per refused option: its flag, its variable (where the environment is
    read), its key in the settings file (where the file holds it) and what is wrong."""
    in_file = read_settings_file(reading.file) if reading.file is not None else {}
    lines = []
    for problem in error.errors(include_url=False):
        said = str(problem["msg"]).removeprefix("Value error, ")  # pydantic's, of a validator
        if not problem["loc"]:  # the settings together (a model validator): its words alone
            lines.append(said)
            continue
        name = str(problem["loc"][0])
        if problem["type"] == "extra_forbidden":  # only a settings file can name one
            lines.append(f"the settings file has {name!r}, which is no setting (see --help)")
            continue
        sources = [cls.variable(name)] if reading.environment else []
        if name in in_file:
            sources.append(f"{name!r} in {reading.file}")
        where = f" ({', '.join(sources)})" if sources else ""
        lines.append(f"--{name.replace('_', '-')}{where}: {said}")
    return "; ".join(lines)


def command_main(
    prog: str,
    description: str,
    settings_cls: type[S],
    run: Callable[[S], int],
) -> Callable[..., int]:
    """A console script's `main(argv=None)`: settings from flags, environment and file, then run."""

    def main(argv: list[str] | None = None) -> int:
        parser = argparse.ArgumentParser(prog=prog, description=description)
        settings_cls.add_arguments(parser)
        return run(parse(parser, settings_cls, sys.argv[1:] if argv is None else argv))

    return main


def main_of_extra(prog: str, requirement: str, module: str) -> Callable[..., int]:
    """A console script's `main(argv=None)` that runs `module`'s `main`, whose packages come
    with an extra (`requirement`, as pip spells it): installed without it, the command
    says which to install (exit 2) instead of failing on an import."""

    def main(argv: list[str] | None = None) -> int:
        try:
            service = importlib.import_module(module)
        except ModuleNotFoundError as missing:
            print(
                f"{prog}: {missing.name} is not installed; the service needs "
                f"pip install '{requirement}'",
                file=sys.stderr,
            )
            return 2
        return int(service.main(argv))

    return main


def parse(parser: argparse.ArgumentParser, settings_cls: type[S], argv: list[str]) -> S:
    """Parse `argv` with `parser` (flags of `settings_cls`) into settings; exit 2 if refused."""
    args = parser.parse_args(argv)
    try:
        return settings_cls.from_args(args)
    except SettingsError as error:
        parser.error(str(error))  # exits 2
