"""`--zenoh-config FILE`: the file is the base, our endpoint, mode and scouting options win."""

from __future__ import annotations

import argparse
import json
import shutil
import socket
from pathlib import Path
from typing import ClassVar

import pytest
import zenoh
from pydantic_settings import SettingsConfigDict

from focustrack_core.wire import router, session


class _Settings(session.ZenohSettings):
    """A service that connects to the default endpoint, as the focus service does."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_ZENOH_TEST_")
    default_connect: ClassVar[tuple[str, ...]] = (session.DEFAULT_ENDPOINT,)


def test_the_file_is_kept_and_our_options_are_written_over_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        """{
          // comments and unquoted keys: JSON5
          mode: "router",
          connect: { endpoints: ["tcp/10.0.0.1:7447"] },
          scouting: { multicast: { enabled: true } },
          transport: { auth: { usrpwd: { user: "focus", password: "secret" } } },
        }"""
    )
    monkeypatch.setenv("FOCUSTRACK_ZENOH_TEST_ZENOH_CONFIG", str(path))  # the environment twin
    config = _Settings.load().zenoh()
    assert json.loads(config.get_json("mode")) == "client"  # only connects: a client
    assert json.loads(config.get_json("connect/endpoints")) == [session.DEFAULT_ENDPOINT]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    usrpwd = json.loads(config.get_json("transport/auth/usrpwd"))
    assert (usrpwd["user"], usrpwd["password"]) == ("focus", "secret")  # from the file

    parser = argparse.ArgumentParser()
    _Settings.add_arguments(parser)
    args = parser.parse_args(["--connect", "tls/zenoh:7447", "--zenoh-config", str(path)])
    endpoints = json.loads(_Settings.from_args(args).zenoh().get_json("connect/endpoints"))
    assert endpoints == ["tls/zenoh:7447"]


@pytest.mark.parametrize(
    ("text", "says"), [(None, "No such file"), ("{mode: router", "expected"), ("{nope: 1}", "nope")]
)
def test_a_config_file_zenoh_cannot_use_is_a_clear_error(
    tmp_path: Path, text: str | None, says: str
) -> None:
    path = tmp_path / "bad.json5"
    if text is not None:
        path.write_text(text)
    with pytest.raises(ValueError, match=f"Zenoh config {path}") as error:
        session.session_config(connect=[session.DEFAULT_ENDPOINT], config_file=path)
    assert says in str(error.value)
    assert router.main(["--listen", session.loopback_endpoint(), "--config", str(path)]) == 2


def test_pixel_tuning_applies_unless_a_config_file_sets_its_own(tmp_path: Path) -> None:
    def tuned(config: zenoh.Config) -> dict[str, int]:
        return {key: json.loads(config.get_json(key)) for key in session.PIXEL_TUNING}

    assert tuned(zenoh.Config()) != session.PIXEL_TUNING  # Zenoh's defaults are other
    assert tuned(session.session_config(listen=[session.DEFAULT_ENDPOINT])) == (
        session.PIXEL_TUNING
    )
    path = tmp_path / "tuned.json5"
    path.write_text("{transport: {link: {tx: {queue: {size: {data: 8}}}}}}")
    config = session.session_config(connect=[session.DEFAULT_ENDPOINT], config_file=path)
    assert tuned(config) == {**session.PIXEL_TUNING, "transport/link/tx/queue/size/data": 8}


def test_a_router_opens_without_waiting_to_scout_unless_a_config_file_says_to(
    tmp_path: Path,
) -> None:
    """Multicast scouting is off, so a router has nothing to scout at open: Zenoh's
    default scouting delay (500 ms) held every router's open that long."""
    config = session.session_config(listen=[session.loopback_endpoint()], mode="router")
    assert json.loads(config.get_json("scouting/delay")) == 0
    path = tmp_path / "scouting.json5"
    path.write_text("{scouting: {delay: 200}}")
    config = session.session_config(listen=[session.DEFAULT_ENDPOINT], config_file=path)
    assert json.loads(config.get_json("scouting/delay")) == 200


def test_shared_memory_room_is_what_the_file_system_has_free(tmp_path: Path) -> None:
    assert session.shared_memory_room_mb(tmp_path / "nowhere") == 0
    free_mb = shutil.disk_usage(tmp_path).free / 1e6
    assert 0 < session.shared_memory_room_mb(tmp_path) == pytest.approx(free_mb, abs=100)


def test_a_port_handed_out_and_not_yet_bound_is_not_handed_out_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A stack picks its services' ports before any binds: the same port twice had one
    service fail with "address already in use"."""
    first = session.free_port()
    picks = iter([first, first, *range(first + 1, first + 100)])
    monkeypatch.setattr(session.secrets, "choice", lambda _: next(picks))
    again = session.free_port()  # `first` is free to a probe, and not handed out again
    assert first < again < first + 100


def test_a_free_port_is_below_the_ephemeral_range_and_bindable() -> None:
    low, high = session.ephemeral_port_range()
    assert 1024 <= low < high
    ports = {session.free_port() for _ in range(20)}
    assert len(ports) > 1  # picked at random
    for port in ports:
        assert session.LOWEST_FREE_PORT <= port < low
        with socket.socket() as server:
            server.bind(("127.0.0.1", port))
