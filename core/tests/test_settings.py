"""One settings model per service: flags, environment and a settings file, each default once."""

from __future__ import annotations

import argparse
import json
from enum import StrEnum
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import pytest
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from focustrack_core.settings import (
    ServiceSettings,
    SettingsError,
    command_main,
    main_of_extra,
    one_of,
)


class DemoSettings(ServiceSettings):
    """A service's settings, as each service declares its own."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_DEMO_")
    list_fields: ClassVar[tuple[str, ...]] = ("connect",)

    port: int = Field(8100, ge=0, le=65535, description="TCP port")
    max_tile_seconds: float = Field(0.1, gt=0, description="computation per tile")
    token: str | None = Field(None, description="bearer token")
    insecure: bool = Field(False, description="serve off loopback without a token")
    family: Literal["standard", "reduced"] = Field("standard", description="map family")
    connect: list[str] | None = Field(None, description="endpoints to connect to")


def settings(argv: list[str], monkeypatch: pytest.MonkeyPatch, **environ: str) -> DemoSettings:
    for name in [*DemoSettings.model_fields, "settings"]:
        monkeypatch.delenv(DemoSettings.variable(name), raising=False)
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    parser = argparse.ArgumentParser()
    DemoSettings.add_arguments(parser)
    return DemoSettings.from_args(parser.parse_args(argv))


def test_the_defaults_are_the_models(monkeypatch: pytest.MonkeyPatch) -> None:
    assert settings([], monkeypatch) == DemoSettings.model_construct(
        port=8100, max_tile_seconds=0.1, token=None, insecure=False, family="standard", connect=None
    )


def test_flags_are_the_fields_in_kebab_case(monkeypatch: pytest.MonkeyPatch) -> None:
    got = settings(
        ["--port", "9000", "--max-tile-seconds", "0.5", "--insecure", "--family", "reduced"],
        monkeypatch,
    )
    assert (got.port, got.max_tile_seconds, got.insecure, got.family) == (
        9000,
        0.5,
        True,
        "reduced",
    )


def test_a_list_takes_items_after_one_flag_repeated_flags_or_commas(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert settings(["--connect", "tcp/a", "tcp/b"], monkeypatch).connect == ["tcp/a", "tcp/b"]
    assert settings(["--connect", "a", "--connect", "b,c"], monkeypatch).connect == ["a", "b", "c"]
    assert settings(["--connect"], monkeypatch).connect == []


def test_the_environment_sets_what_no_flag_does(monkeypatch: pytest.MonkeyPatch) -> None:
    got = settings(
        ["--port", "9001"],
        monkeypatch,
        FOCUSTRACK_DEMO_PORT="9000",
        FOCUSTRACK_DEMO_TOKEN="secret",
        FOCUSTRACK_DEMO_INSECURE="yes",
        FOCUSTRACK_DEMO_CONNECT="tcp/1 tcp/2,tcp/3",
    )
    assert (got.port, got.token, got.insecure) == (9001, "secret", True)  # the flag wins
    assert got.connect == ["tcp/1", "tcp/2", "tcp/3"]
    assert settings([], monkeypatch, FOCUSTRACK_DEMO_INSECURE="").insecure is False


@pytest.mark.parametrize("suffix", [".toml", ".json", ".TOML"])
def test_a_settings_file_is_under_the_environment_and_flags(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str
) -> None:
    file = tmp_path / f"demo{suffix}"
    values = {"port": 7000, "max_tile_seconds": 0.3, "token": "from-file"}
    if suffix.lower() == ".toml":  # .TOML too: it used to be read as JSON
        file.write_text("port = 7000\nmax_tile_seconds = 0.3\ntoken = 'from-file'\n")
    else:
        file.write_text(json.dumps(values))
    got = settings(["--settings", str(file), "--port", "7001"], monkeypatch)
    assert (got.port, got.max_tile_seconds, got.token) == (7001, 0.3, "from-file")
    by_env = settings([], monkeypatch, FOCUSTRACK_DEMO_SETTINGS=str(file), FOCUSTRACK_DEMO_PORT="1")
    assert (by_env.port, by_env.max_tile_seconds) == (1, 0.3)


@pytest.mark.parametrize(
    ("argv", "environ", "needle"),
    [
        (["--port", "70000"], {}, "--port (FOCUSTRACK_DEMO_PORT): Input should be less than"),
        (["--max-tile-seconds", "0"], {}, "--max-tile-seconds"),
        ([], {"FOCUSTRACK_DEMO_PORT": "eighty"}, "--port (FOCUSTRACK_DEMO_PORT): Input should be"),
    ],
)
def test_a_refused_value_names_its_option(
    monkeypatch: pytest.MonkeyPatch, argv: list[str], environ: dict[str, str], needle: str
) -> None:
    with pytest.raises(SettingsError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        settings(argv, monkeypatch, **environ)


def test_a_refused_value_from_the_settings_file_names_its_key_there(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The user looks in the file: the message names its key there beside the flag and the
    variable (it named only those two, neither of which was set)."""
    file = tmp_path / "demo.toml"
    file.write_text("port = 70000\nmax_tile_seconds = 0.2\n")
    with pytest.raises(SettingsError) as refused:
        settings(["--settings", str(file)], monkeypatch)
    assert f"--port (FOCUSTRACK_DEMO_PORT, 'port' in {file}): Input should be" in str(refused.value)
    assert "max_tile_seconds" not in str(refused.value)  # a good value is not named


def test_an_unknown_key_or_a_bad_file_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    typo = tmp_path / "typo.toml"
    typo.write_text("prot = 1\n")
    # named as the file's key, not as a flag and a variable that do not exist
    with pytest.raises(SettingsError, match="the settings file has 'prot', which is no setting"):
        settings(["--settings", str(typo)], monkeypatch)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(SettingsError, match=r"broken\.json"):
        settings(["--settings", str(broken)], monkeypatch)
    yaml = tmp_path / "demo.yaml"
    yaml.write_text("port: 7000\n")
    with pytest.raises(SettingsError, match=r"read as JSON: a TOML file's name ends in \.toml"):
        settings(["--settings", str(yaml)], monkeypatch)
    with pytest.raises(SettingsError, match=r"missing\.toml"):
        settings(["--settings", str(tmp_path / "missing.toml")], monkeypatch)


def test_a_choice_outside_a_literal_is_an_argparse_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        settings(["--family", "odd"], monkeypatch)
    assert exit_.value.code == 2
    assert "invalid choice: 'odd'" in capsys.readouterr().err


def test_help_names_each_variable_and_default(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    DemoSettings.add_arguments(parser)
    text = " ".join(parser.format_help().split())
    assert "--max-tile-seconds" in text and "FOCUSTRACK_DEMO_MAX_TILE_SECONDS" in text
    assert "--settings FILE" in text and "FOCUSTRACK_DEMO_SETTINGS" in text
    assert "--insecure, --no-insecure" in text


def test_a_console_script_exits_2_on_a_refused_value(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("FOCUSTRACK_DEMO_PORT", raising=False)
    seen: list[DemoSettings] = []
    main = command_main("demo", "a demo", DemoSettings, lambda s: seen.append(s) or 0)
    assert main(["--port", "81"]) == 0 and seen[0].port == 81
    with pytest.raises(SystemExit) as exit_:
        main(["--port", "-1"])
    assert exit_.value.code == 2
    assert "--port (FOCUSTRACK_DEMO_PORT)" in capsys.readouterr().err


class Colour(StrEnum):
    RED = "red-ish"
    BLUE = "blue-ish"


class PaintSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_PAINT_")

    colour: Colour = Field(Colour.RED, description="a colour")


def test_an_enum_takes_its_values_as_choices(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    PaintSettings.add_arguments(parser)
    assert "--colour {red-ish,blue-ish}" in parser.format_help()
    assert (
        PaintSettings.from_args(parser.parse_args(["--colour", "blue-ish"])).colour is Colour.BLUE
    )
    with pytest.raises(SystemExit):
        parser.parse_args(["--colour", "BLUE"])
    assert "invalid choice: 'BLUE'" in capsys.readouterr().err


def test_flags_alone_read_neither_the_environment_nor_a_file(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("FOCUSTRACK_DEMO_PORT", "9000")
    parser = argparse.ArgumentParser()
    DemoSettings.add_arguments(parser, environment=False)
    text = parser.format_help()
    assert "--settings" not in text and "FOCUSTRACK_DEMO" not in text
    got = DemoSettings.from_args(parser.parse_args(["--family", "reduced"]), environment=False)
    assert (got.port, got.family) == (8100, "reduced")
    assert DemoSettings.load(environment=False).port == 8100
    assert DemoSettings.load().port == 9000  # the environment again, as before
    with pytest.raises(SettingsError) as refused:
        DemoSettings.from_args(parser.parse_args(["--port", "-1"]), environment=False)
    assert str(refused.value).startswith("--port: Input should be")  # no variable it ignores


def test_a_choice_known_at_run_time_is_checked_and_listed(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    class Chosen(ServiceSettings):
        model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_CHOSEN_")
        metric: Annotated[str, one_of(["brenner", "tenengrad"])] = "brenner"

    monkeypatch.setenv("FOCUSTRACK_CHOSEN_METRIC", "sobel")
    with pytest.raises(SettingsError, match="'sobel' is not one of brenner, tenengrad"):
        Chosen.load()
    parser = argparse.ArgumentParser()
    Chosen.add_arguments(parser)
    assert "--metric {brenner,tenengrad}" in parser.format_help()


def test_an_empty_settings_variable_is_no_file(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FOCUSTRACK_DEMO_SETTINGS", "")
    monkeypatch.delenv("FOCUSTRACK_DEMO_PORT", raising=False)
    assert DemoSettings.load().port == 8100


def test_a_command_whose_extra_is_missing_says_which_to_install(capsys) -> None:
    main = main_of_extra("focustrack-thing", "focustrack-thing[service]", "no_such_module_x")
    assert main([]) == 2
    error = capsys.readouterr().err
    assert "no_such_module_x is not installed" in error
    assert "pip install 'focustrack-thing[service]'" in error
