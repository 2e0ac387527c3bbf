"""Deployment files agree with the code: compose.yaml and compose.facility.yaml, each
service's Dockerfile and lock export.

What is checked without a container engine: every compose service builds from its own
Dockerfile, runs its own console script configured by environment variables that the
script's parser accepts, and probes its health with flags the probe accepts; each
image installs exactly the versions of uv.lock. The facility's replicas, routers and
scanners are wired as docs/facility.md says (routers meshed, HAProxy's backends the
replicas, each scanner's services on one router). (Building and running the images is
the containerized end-to-end test's job.)
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import shutil
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from focustrack.bus_secrets import PUBLIC_FILES, ROLES, write_bus_files
from focustrack.cli import main
from focustrack_core import health
from focustrack_core.settings import ServiceSettings
from focustrack_core.wire import router

ROOT = Path(__file__).resolve().parents[1]
#: compose service -> (its folder under services/, the module of its console script)
SERVICES = {
    "instrument": ("instrument_sim", "focustrack_instrument_sim.service"),
    "focus": ("focus", "focustrack_focus.service"),
    "estimator": ("estimator", "focustrack_estimator.service"),
    "phase": ("phase", "focustrack_phase.service"),
    "scheduler": ("scheduler", "focustrack_scheduler.scan"),
}


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "compose.yaml").read_text())


def defaults(value: Any) -> str:
    """A compose value with every `${NAME:-default}` taken at its default."""
    return re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", str(value))


def configured(
    module_name: str, environ: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> tuple[str, set[str], Any]:
    """A service command's environment prefix, the variables it reads, and its settings as
    `environ` sets them (nothing else in the environment)."""
    settings_cls = importlib.import_module(module_name).Settings
    assert issubclass(settings_cls, ServiceSettings), module_name
    variables = {settings_cls.variable(name) for name in settings_cls.model_fields}
    for name in [*variables, settings_cls.variable("settings")]:
        monkeypatch.delenv(name, raising=False)
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    return settings_cls.env_prefix(), variables, settings_cls.load()


def test_every_service_is_its_own_image(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert set(services) == {"zenoh", *SERVICES}
    for name, (folder, _) in SERVICES.items():
        build = services[name]["build"]
        assert build["context"] == "."
        assert build["dockerfile"] == f"services/{folder}/Dockerfile"
        assert (ROOT / build["dockerfile"]).exists()
        assert "BASE_IMAGE" in build["args"]
        assert "entrypoint" not in services[name] and "command" not in services[name]


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_each_dockerfile_runs_its_distributions_console_script(name: str) -> None:
    folder, module = SERVICES[name]
    dockerfile = (ROOT / "services" / folder / "Dockerfile").read_text()
    project = tomllib.loads((ROOT / "services" / folder / "pyproject.toml").read_text())["project"]
    (script, target), *_ = project["scripts"].items()
    # the service's main, or a guard that runs it where its extra is installed
    assert target in (f"{module}:main", f"{module.rsplit('.', 1)[0]}.command:main")
    assert f'ENTRYPOINT ["{script}"]' in dockerfile
    assert "ARG BASE_IMAGE=" in dockerfile and "USER focustrack" in dockerfile
    assert f"-r /src/services/{folder}/requirements.txt" in dockerfile and "--no-deps" in dockerfile


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_each_service_is_configured_by_environment_its_command_accepts(
    compose: dict[str, Any], name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    service = compose["services"][name]
    environ = {key: defaults(value) for key, value in service["environment"].items()}
    prefix, options, args = configured(SERVICES[name][1], environ, monkeypatch)
    unknown = [key for key in environ if not key.startswith(prefix)]
    assert not unknown, f"{name}: variables its command does not read: {unknown}"
    assert set(environ) <= options, f"{name}: no such option: {set(environ) - options}"
    if name not in ("estimator", "phase"):  # the two on REST alone
        assert args.connect == ["tcp/zenoh:7447"]
    if name == "estimator":
        assert args.store.startswith("/data/") and args.host == "0.0.0.0"
    if name == "scheduler":
        assert args.estimator == "http://estimator:8100" and args.out.parts[1] == "out"
        assert args.no_progress is True
        assert args.live_port == 8200 and args.live_host == "0.0.0.0"  # published: /healthz


def test_health_checks_volume_and_the_scheduler_job(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name in ("instrument", "focus", "estimator", "phase", "scheduler"):
        check = services[name]["healthcheck"]
        test = [defaults(word) for word in check["test"]]
        assert test[:4] == ["CMD", "python3", "-m", "focustrack_core.health"]
        probe = health.parser().parse_args(test[4:])
        assert probe.http or (probe.instrument == "sim" and probe.connect == ["tcp/zenoh:7447"])
        assert {"interval", "timeout", "retries"} <= set(check)
    volume, mount = services["estimator"]["volumes"][0].split("#")[0].strip().split(":")
    assert volume in compose["volumes"] and mount == "/data"
    scheduler = services["scheduler"]
    assert scheduler["restart"] == "on-failure"  # a job, resumed after a failure
    assert set(scheduler["depends_on"]) == {"instrument", "focus", "estimator"}
    assert all(c == {"condition": "service_healthy"} for c in scheduler["depends_on"].values())


def test_each_services_requirements_are_the_lock_files(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location(
        "export", ROOT / "scripts" / "export_requirements.py"
    )
    assert spec is not None and spec.loader is not None
    export = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(export)
    for service in export.SERVICES:
        checked_in = (ROOT / "services" / service / "requirements.txt").read_text()
        assert checked_in == export.export(service), f"{service}: stale, run `make lock`"


def test_services_run_on_a_read_only_root_and_the_router_can_be_ours(
    compose: dict[str, Any],
) -> None:
    services = compose["services"]
    for name in SERVICES:
        assert services[name]["read_only"] is True and services[name]["tmpfs"] == ["/tmp"]
    zenoh = services["zenoh"]
    assert defaults(zenoh["image"]) == "eclipse/zenoh:1.10.2"  # the official router for labs
    assert defaults(zenoh["entrypoint"]) == "/entrypoint.sh"  # that image's own
    # Our router (ZENOH_ENTRYPOINT, where the official image cannot be pulled) takes the
    # same command; tests/test_containers.py runs it.
    args = router.parser().parse_args(zenoh["command"])
    assert args.listen == ["tcp/0.0.0.0:7447"] and args.no_multicast_scouting


def test_the_secure_overlay_configures_every_role_with_options_its_command_accepts(
    compose: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    secure = yaml.safe_load((ROOT / "compose.secure.yaml").read_text())
    services = secure["services"]
    assert set(services) == {"zenoh", "instrument", "focus", "phase", "scheduler"}  # no estimator
    for spec in services.values():
        assert [defaults(v) for v in spec["volumes"]] == ["./deploy/secrets:/run/focustrack:ro"]
        assert "ports" not in spec
    args = router.parser().parse_args(services["zenoh"]["command"])
    assert args.listen == ["tls/0.0.0.0:7447"]
    assert str(args.zenoh_config) == "/run/focustrack/router.json5"
    for name in ("instrument", "focus", "phase", "scheduler"):
        merged = compose["services"][name]["environment"] | services[name]["environment"]
        environ = {key: defaults(value) for key, value in merged.items()}
        _, _, args = configured(SERVICES[name][1], environ, monkeypatch)
        assert args.connect == ["tls/zenoh:7447"]
        assert str(args.zenoh_config) == f"/run/focustrack/{name}.json5"
        if name != "instrument":
            assert str(args.result_key_file) == "/run/focustrack/result.key"
        else:
            assert args.serve_truth is False and args.queue_depth >= 1
        if name != "scheduler":
            assert str(args.frame_key_file) == "/run/focustrack/frame.key"
    probe = [defaults(word) for word in services["instrument"]["healthcheck"]["test"]]
    checked = health.parser().parse_args(probe[4:])
    assert checked.connect == ["tls/zenoh:7447"]
    assert str(checked.zenoh_config) == "/run/focustrack/health.json5"

    # `focustrack bus secrets` writes every file those paths name, each a valid Zenoh config.
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is needed for `focustrack bus secrets`")
    write_bus_files(tmp_path, ["zenoh"], Path("/run/focustrack"))
    for role in ("router", *ROLES):
        config = zenoh.Config.from_file(str(tmp_path / f"{role}.json5"))
        assert "/run/focustrack/" in config.get_json("transport")
    assert (tmp_path / "result.key").stat().st_size > 32
    assert (tmp_path / "frame.key").read_text() != (tmp_path / "result.key").read_text()
    assert (tmp_path / "frame.key").stat().st_size > 32
    assert not (tmp_path / "ca.key").exists()  # nobody who reads the folder can sign
    users = (tmp_path / "credentials.txt").read_text().split()
    assert sorted(line.split(":")[0] for line in users) == sorted(ROLES)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="`bus secrets` needs openssl")
def test_bus_secrets_are_their_owners_alone_and_given_to_the_containers_user(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The router's key and the passwords for one user only; with --owner, the user every
    FocusTrack image runs as (10001), who could not read a root-owned 0600 key otherwise."""
    mine = tmp_path / "mine"
    assert main(["bus", "secrets", str(mine), "--host", "zenoh"]) == 0
    assert "--owner 10001" in capsys.readouterr().out  # what a container deployment needs
    modes = {path.name: path.stat().st_mode & 0o777 for path in mine.iterdir()}
    assert modes == {name: 0o644 if name in PUBLIC_FILES else 0o600 for name in modes}
    assert mine.stat().st_mode & 0o777 == 0o700 and "router.key" in modes
    if os.geteuid() != 0:
        assert main(["bus", "secrets", str(tmp_path / "theirs"), "--owner", "10001"]) == 1
        assert "needs root" in capsys.readouterr().err
        return
    theirs = tmp_path / "theirs"
    assert main(["bus", "secrets", str(theirs), "--owner", "10001"]) == 0
    assert {path.stat().st_uid for path in [theirs, *theirs.iterdir()]} == {10001}


# --- compose.facility.yaml: replicas on PostgreSQL, two routers, three scanners ------------


@pytest.fixture(scope="module")
def facility() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "compose.facility.yaml").read_text())


def focustrack_service(name: str) -> str:
    """The compose.yaml service that a facility service is one of: `instrument-2` is an
    `instrument`, `estimator-a` an `estimator` (the facility's `estimator` is HAProxy: none)."""
    return name.rpartition("-")[0]


def test_the_facility_configures_each_service_with_environment_its_command_accepts(
    facility: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    services = facility["services"]
    routers = {"tcp/zenoh-a:7447", "tcp/zenoh-b:7447"}
    used: dict[str, set[str]] = {}
    for name, service in services.items():
        kind = focustrack_service(name)
        if kind not in SERVICES:
            continue
        assert service["build"]["dockerfile"] == f"services/{SERVICES[kind][0]}/Dockerfile"
        environ = {key: defaults(value) for key, value in service["environment"].items()}
        prefix, options, args = configured(SERVICES[kind][1], environ, monkeypatch)
        assert all(key.startswith(prefix) for key in environ), name
        assert set(environ) <= options, f"{name}: no such option: {set(environ) - options}"
        if kind == "estimator":
            assert args.store == "postgresql://focustrack:@postgres:5432/focustrack"
            assert args.host == "0.0.0.0" and args.port == 8100
            continue
        (endpoint,) = args.connect
        assert endpoint in routers, name
        used.setdefault(endpoint, set()).add(name)
        if kind == "instrument":
            probe = health.parser().parse_args(
                [defaults(w) for w in service["healthcheck"]["test"][4:]]
            )
            assert probe.instrument == args.name and probe.connect == [endpoint]
        if kind == "scheduler":
            assert args.estimator == "http://estimator:8100"  # HAProxy
            scanner = name.rsplit("-", 1)[1]
            assert args.instrument == f"scanner-{scanner}" and args.out.name == f"scanner-{scanner}"
            # a slide its own instrument holds (the simulator's slide-0, slide-1, ...)
            held = services[f"instrument-{scanner}"]["environment"]["FOCUSTRACK_INSTRUMENT_SLIDES"]
            assert args.slide in {f"slide-{i}" for i in range(int(held))}
        if kind == "focus":  # it reads the slide its scanner's scheduler scans, only
            scheduler = services[f"scheduler-{name.rsplit('-', 1)[1]}"]["environment"]
            assert args.slides == defaults(scheduler["FOCUSTRACK_SCAN_SLIDE"]), name
        if kind in {"instrument", "scheduler"}:  # metrics for a Prometheus on the network
            assert args.metrics_port == 9100 and args.metrics_host == "0.0.0.0", name
    assert set(used) == routers  # the scanners' services spread over both routers
    slides = {
        defaults(services[f"scheduler-{n}"]["environment"]["FOCUSTRACK_SCAN_SLIDE"])
        for n in (1, 2, 3)
    }
    assert len(slides) == 3  # each scanner on a slide of its own


def test_the_facility_meshes_its_routers_and_balances_its_replicas(
    facility: dict[str, Any],
) -> None:
    services = facility["services"]
    for name, other in (("zenoh-a", "zenoh-b"), ("zenoh-b", "zenoh-a")):
        args = router.parser().parse_args(services[name]["command"])
        assert args.listen == ["tcp/0.0.0.0:7447"] and args.connect == [f"tcp/{other}:7447"]
        assert defaults(services[name]["entrypoint"]) == "/entrypoint.sh"  # zenohd's image
    postgres = services["postgres"]["environment"]
    assert postgres["POSTGRES_USER"] == postgres["POSTGRES_DB"] == "focustrack"
    assert (ROOT / services["postgres"]["build"]["dockerfile"]).exists()
    balancer = services["estimator"]
    assert (ROOT / balancer["build"]["dockerfile"]).exists()
    (mount,) = balancer["volumes"]
    source, target, mode = mount.split(":")
    assert target == "/usr/local/etc/haproxy/haproxy.cfg" and mode == "ro"
    config = (ROOT / source).read_text()
    backends = re.findall(r"^\s*server (\S+) (\S+):(\d+)", config, re.M)
    assert backends == [
        ("estimator-a", "estimator-a", "8100"),
        ("estimator-b", "estimator-b", "8100"),
    ]
    assert all(
        services[name]["environment"]["FOCUSTRACK_ESTIMATOR_PORT"] == "8100"
        for name, *_ in backends
    )
    assert re.search(r"^\s*bind :8100$", config, re.M)
    assert defaults(balancer["ports"][0]).endswith(":8100")


def test_the_facility_takes_its_secrets_from_the_env_file() -> None:
    text = (ROOT / "compose.facility.yaml").read_text()
    secrets = set(re.findall(r"\$\{(\w+_(?:TOKEN|PASSWORD))", text))
    assert secrets == {"FOCUSTRACK_ESTIMATOR_TOKEN", "POSTGRES_PASSWORD"}
    example = (ROOT / ".env.example").read_text()
    assert all(re.search(rf"^{name}=\S+", example, re.M) for name in secrets)
