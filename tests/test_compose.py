"""compose.yaml is valid: its services, images, health checks and volume, and every command it
runs is a `focustrack` command line our own parsers accept (no Docker engine runs here)."""

from __future__ import annotations

import argparse
import importlib
import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

from focustrack.cli import COMMANDS
from focustrack.services.scheduler import health
from focustrack.services.scheduler.scan import BEST_KALMAN

ROOT = Path(__file__).resolve().parents[1]
SERVICES = {"zenoh", "instrument", "focus", "estimator", "scheduler"}


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "compose.yaml").read_text())


def environment(service: dict[str, Any]) -> dict[str, str]:
    """The service's variables with compose's `${NAME:-default}` taken at its default."""
    return {
        name: re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", str(value))
        for name, value in service.get("environment", {}).items()
    }


def shell_words(text: str, variables: dict[str, str]) -> list[str]:
    """A `sh -c` line as the container's shell runs it: `$$X` is compose's escape for `$X`."""
    text = text.replace("$$", "$")
    for name in sorted(variables, key=len, reverse=True):
        text = text.replace(f"${name}", variables[name])
    assert "$" not in text, f"unset variable in {text!r}"
    return shlex.split(text)


def test_services_images_and_builds(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert set(services) == SERVICES
    assert services["zenoh"]["image"].startswith("eclipse/zenoh:")
    assert "7447" in " ".join(services["zenoh"]["command"])
    for name in SERVICES - {"zenoh"}:
        assert services[name]["build"] == "."  # the Dockerfile at the root
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert dockerfile.startswith("#") and "FROM python:3.11" in dockerfile
    assert 'ENTRYPOINT ["focustrack"]' in dockerfile


def test_health_checks_volume_and_the_scheduler_job(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name in ("instrument", "focus", "estimator"):
        check = services[name]["healthcheck"]
        assert check["test"][0] == "CMD-SHELL" and "health" in check["test"][1]
        assert {"interval", "timeout", "retries"} <= set(check)
    volume, mount = services["estimator"]["volumes"][0].split("#")[0].strip().split(":")
    assert volume in compose["volumes"] and mount == "/data"
    scheduler = services["scheduler"]
    assert scheduler["restart"] == "on-failure"  # a job, resumed after a failure
    assert all(
        condition == {"condition": "service_healthy"}
        for condition in scheduler["depends_on"].values()
    )
    assert set(scheduler["depends_on"]) == {"instrument", "focus", "estimator"}
    assert environment(scheduler)["STRATEGY"] == BEST_KALMAN


@pytest.mark.parametrize("name", sorted(SERVICES - {"zenoh"}))
def test_every_command_parses_with_the_focustrack_cli(compose: dict[str, Any], name: str) -> None:
    service = compose["services"][name]
    assert service["entrypoint"] == ["sh", "-c"]
    words = shell_words(service["command"][0], environment(service))
    assert words[:2] == ["exec", "focustrack"]
    words = words[2:]
    command = next(c for c in COMMANDS if words[: len(c.split())] == c.split())
    parser = argparse.ArgumentParser()
    importlib.import_module(COMMANDS[command][0]).add_arguments(parser)
    args = parser.parse_args(words[len(command.split()) :])  # exits (fails) on a bad flag
    if name != "estimator":
        assert args.connect == ["tcp/zenoh:7447"]
    if name == "estimator":
        assert args.store.startswith("/data/")
    if name == "scheduler":
        assert args.estimator == "http://estimator:8100" and args.out.parts[1] == "out"
    check = service.get("healthcheck")
    if check is not None:  # the probe's flags parse too
        probe = shell_words(check["test"][1], environment(service))
        assert probe[:3] == ["python", "-m", "focustrack.services.scheduler.health"]
        probe_args = health.parser().parse_args(probe[3:])
        assert probe_args.http or probe_args.instrument == "sim"
