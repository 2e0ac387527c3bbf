"""The estimator's settings: one model for its flags and environment, and the refusals at start
(a value out of bounds, an open address without a token, a module without strategies)."""

from __future__ import annotations

from pathlib import Path

import pytest

from focustrack_estimator.service import main, run
from focustrack_estimator.settings import EstimatorSettings

#: The command's options, as its users know them (flags and FOCUSTRACK_ESTIMATOR_ variables).
OPTIONS = [
    "otlp-endpoint", "host", "port", "store", "store-timeout-s", "token", "insecure",
    "max-body-bytes", "max-grid-side", "max-grid-tiles", "snapshot-every", "body-timeout-s",
    "max-slide-bytes",
    "max-tile-seconds", "max-live-slides", "max-live-bytes", "strategies-from", "access-log",
]  # fmt: skip


@pytest.fixture(autouse=True)
def _no_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("settings", *EstimatorSettings.model_fields):
        monkeypatch.delenv(EstimatorSettings.variable(name), raising=False)


def test_every_option_keeps_its_flag_and_variable(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    usage = capsys.readouterr().out
    for option in OPTIONS:
        assert f"--{option}" in usage
        assert f"FOCUSTRACK_ESTIMATOR_{option.upper().replace('-', '_')}" in usage
    assert [name.replace("_", "-") for name in EstimatorSettings.model_fields] == OPTIONS


def test_the_environment_sets_and_an_empty_token_unsets(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FOCUSTRACK_ESTIMATOR_MAX_TILE_SECONDS", "0.25")
    monkeypatch.setenv("FOCUSTRACK_ESTIMATOR_TOKEN", "")
    settings = EstimatorSettings.load()
    assert settings.max_tile_seconds == 0.25 and settings.token is None
    assert EstimatorSettings(token="").token is None  # `--token ''`: no auth, as before


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--max-live-slides", "0"], "--max-live-slides"),
        (["--max-tile-seconds", "-1"], "--max-tile-seconds"),
        (["--snapshot-every", "0"], "--snapshot-every"),
        (["--store-timeout-s", "0"], "--store-timeout-s"),
        (["--port", "70000"], "--port"),
        # a limit that admits no slide's configuration: every creation was a 413
        (["--max-body-bytes", "10"], "--max-body-bytes"),
        # a token no client can send in a header: every request was a 401
        (["--token", " "], "Authorization header"),
        (["--token", "secret\n"], "Authorization header"),
    ],
)
def test_a_refused_value_exits_2_naming_the_option(
    flags: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        main(flags)
    assert exited.value.code == 2 and named in capsys.readouterr().err


def test_an_open_address_without_a_token_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = tmp_path / "estimator.sqlite"
    assert run(EstimatorSettings(host="0.0.0.0", store=str(store))) == 2
    assert "without a token" in capsys.readouterr().err and not store.exists()


def test_a_module_without_strategies_is_refused_before_the_store_is_touched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = tmp_path / "estimator.sqlite"
    assert run(EstimatorSettings(strategies_from="json", store=str(store))) == 2
    assert "no CATALOGUE there" in capsys.readouterr().err and not store.exists()
