"""Compose files run with Podman, for the container tests (test_containers, test_facility).

`Topology` reads compose files (merged in order, as compose's `-f`) and runs their
services as Podman containers on a network of the test's own: image, entry point,
command, environment, volumes, tmpfs, read-only root, health check, depends_on (not
`restart`: the tests play the orchestrator). No registry can be reached here, so the
images' base is built from Debian's packages with debootstrap (`ensure_base_image`, once
per machine: it stays in Podman's store as BASE_TAG, with the host's CA bundle for pip).
Podman, runc and debootstrap are installed with apt-get when missing and the tests run as
root (`ensure_engine`); elsewhere they skip, saying what is missing.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shlex
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml

from focustrack_scheduler import outputs

ROOT = Path(__file__).resolve().parents[1]
#: The base image built from Debian's packages, kept in Podman's store between runs.
BASE_TAG = "localhost/focustrack-base:bookworm"


def debian_mirror() -> str:
    """The Debian mirror this machine's apt uses (FOCUSTRACK_DEBIAN_MIRROR overrides it)."""
    if os.environ.get("FOCUSTRACK_DEBIAN_MIRROR"):
        return os.environ["FOCUSTRACK_DEBIAN_MIRROR"]
    sources = [Path("/etc/apt/sources.list"), *sorted(Path("/etc/apt/sources.list.d").glob("*"))]
    for source in sources:
        text = source.read_text() if source.is_file() else ""
        for match in re.finditer(r"^(?:URIs:\s*|deb\s+(?:\[[^]]*\]\s+)?)(\S+)", text, re.M):
            if match[1].rstrip("/").endswith("/debian"):  # not -security or a third party's
                return match[1]
    pytest.skip("containers: no Debian mirror in apt's sources for debootstrap")


#: Settings each needed on these machines (docs: ENGINEERING_NOTES, "Containers"): crun
#: fails on hybrid cgroups, and the sandbox forbids raising rlimits.
PODMAN = ["podman", "--runtime", "runc", "--cgroup-manager", "cgroupfs"]
ULIMITS = ["--ulimit", "nofile=1024:1024", "--ulimit", "nproc=1000:1000"]
TOOLS = ("podman", "runc", "debootstrap")  # Debian packages, each named as its command
HEALTHY_TIMEOUT_S = 120.0
#: Held while an image is built: the test files that build the same images (test_containers,
#: test_facility) run on two pytest workers at once, and two builds of one layer at the same
#: time both do the work; one after the other, the second finds the layer in Podman's cache.
BUILD_LOCK = Path(tempfile.gettempdir()) / "focustrack-podman-build.lock"


def say(config: pytest.Config, message: str, topic: str = "containers") -> None:
    """Progress and figures on the terminal as the test runs (not only on failure)."""
    capture = config.pluginmanager.getplugin("capturemanager")
    with capture.global_and_fixture_disabled():
        print(f"[{topic}] {message}", flush=True)


def podman(*args: str, check: bool = True, timeout_s: float = 600) -> subprocess.CompletedProcess:
    run = subprocess.run(
        [*PODMAN, *args], capture_output=True, text=True, timeout=timeout_s, check=False
    )
    if check and run.returncode != 0:
        raise AssertionError(f"podman {' '.join(args)} failed:\n{run.stdout}\n{run.stderr}")
    return run


@contextmanager
def build_lock() -> Iterator[None]:
    """BUILD_LOCK held (an exclusive flock, let go when the block ends or the process dies)."""
    with BUILD_LOCK.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def ensure_engine() -> None:
    """Install Podman, runc and debootstrap with apt-get when missing; skip when impossible."""
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        if os.geteuid() != 0 or shutil.which("apt-get") is None:
            pytest.skip(f"containers: {', '.join(missing)} missing, and no root with apt-get")
        install = ["apt-get", "install", "-y", *missing]  # as checked: with recommends
        env = os.environ | {"DEBIAN_FRONTEND": "noninteractive"}
        if subprocess.run(install, capture_output=True, env=env).returncode != 0:
            subprocess.run(["apt-get", "update"], capture_output=True, env=env)
            done = subprocess.run(install, capture_output=True, text=True, env=env)
            if done.returncode != 0:
                pytest.skip(f"containers: apt-get could not install {missing}: {done.stderr}")
    info = subprocess.run([*PODMAN, "info"], capture_output=True, text=True)
    if info.returncode != 0:
        pytest.skip(f"containers: podman cannot run here: {info.stderr.strip()[-500:]}")


def ensure_base_image(config: pytest.Config) -> tuple[str, float]:
    """BASE_IMAGE from the environment, else the debootstrap base (built once per machine);
    seconds the build took (0: there was one)."""
    if os.environ.get("BASE_IMAGE"):
        return os.environ["BASE_IMAGE"], 0.0
    with build_lock():  # a test file on the other worker may be building it
        return _debootstrap_base_image(config)


def _debootstrap_base_image(config: pytest.Config) -> tuple[str, float]:
    """BASE_TAG, built with debootstrap unless Podman's store has it; seconds the build took."""
    if podman("image", "exists", BASE_TAG, check=False).returncode == 0:
        return BASE_TAG, 0.0
    if os.geteuid() != 0:
        pytest.skip("containers: building the Debian base image with debootstrap needs root")
    mirror = debian_mirror()
    say(config, f"building {BASE_TAG} with debootstrap from {mirror} (once per machine)")
    started_s = time.monotonic()
    with tempfile.TemporaryDirectory(dir="/var/tmp") as scratch:
        rootfs = Path(scratch) / "rootfs"
        # python3 in the base: the Dockerfiles install it with apt only when it is absent.
        packages = "--include=python3,python3-venv,ca-certificates"
        debootstrap = ["debootstrap", "--variant=minbase", packages, "bookworm", str(rootfs)]
        subprocess.run([*debootstrap, mirror], check=True, capture_output=True)
        # pip inside a build must trust what the host trusts (the host's CA bundle, at a
        # path of its own: over the image's own bundle it would break ca-certificates).
        shutil.copy("/etc/ssl/certs/ca-certificates.crt", rootfs / "etc" / "host-ca.crt")
        tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
        change = ["--change", "ENV PIP_CERT=/etc/host-ca.crt"]
        imported = subprocess.run(
            [*PODMAN, "import", *change, "-", BASE_TAG], stdin=tar.stdout, capture_output=True
        )
        assert tar.wait() == 0 and imported.returncode == 0, imported.stderr
    built_s = round(time.monotonic() - started_s, 1)
    say(config, f"base image built in {built_s} s")
    return BASE_TAG, built_s


# --- compose.yaml, read and run with podman ------------------------------------------------

VARIABLE = re.compile(r"\$\{(\w+)(?::-([^}]*))?\}")


def interpolate(value: Any, variables: Mapping[str, str]) -> Any:
    """`${NAME}` and `${NAME:-default}` in every string of `value`, as compose does."""
    if isinstance(value, str):
        return VARIABLE.sub(lambda m: variables.get(m[1]) or (m[2] or ""), value)
    if isinstance(value, list):
        return [interpolate(item, variables) for item in value]
    if isinstance(value, dict):
        return {key: interpolate(item, variables) for key, item in value.items()}
    return value


#: Compose's keys whose lists an override file extends (others it replaces).
EXTENDED_LISTS = ("volumes", "ports", "tmpfs")


def merge_compose(base: Any, override: Any, key: str = "") -> Any:
    """`override` over `base`, as `docker compose -f base -f override` merges them: maps
    merged key by key, the lists of `EXTENDED_LISTS` extended, any other value replaced."""
    if isinstance(base, dict) and isinstance(override, dict):
        merged = dict(base)
        for name, value in override.items():
            merged[name] = merge_compose(base[name], value, name) if name in base else value
        return merged
    if isinstance(base, list) and isinstance(override, list) and key in EXTENDED_LISTS:
        return [*base, *override]
    return override


class Topology:
    """compose files' services as Podman containers on a network of the test's own.

    Containers, volumes and the network are named PROJECT-NAME; each service is also
    reachable by its compose name on the network, as under compose. `variables` play
    the part of compose's .env file; `files` are merged in order, as compose's `-f`.
    """

    def __init__(
        self, project: str, variables: Mapping[str, str], files: tuple[str, ...] = ("compose.yaml",)
    ) -> None:
        self.compose: dict[str, Any] = {}
        for name in files:
            self.compose = merge_compose(self.compose, yaml.safe_load((ROOT / name).read_text()))
        self.project = project
        self.variables = dict(variables)
        self.network = f"{project}-net"
        self.started_s: dict[str, float] = {}
        self.containers: list[str] = []

    def spec(self, service: str, **variables: str) -> dict[str, Any]:
        """`service` of compose.yaml with its variables filled in (these before the others)."""
        return dict(interpolate(self.compose["services"][service], self.variables | variables))

    def name(self, container: str) -> str:
        return f"{self.project}-{container}"

    def build(self, service: str, base_image: str) -> float:
        """Build `service`'s image as compose would, on `base_image`; seconds taken."""
        spec = self.spec(service, BASE_IMAGE=base_image)
        build_args = [f"--build-arg={key}={value}" for key, value in spec["build"]["args"].items()]
        with build_lock():  # seconds taken: the build's own, not the wait for the lock
            started_s = time.monotonic()
            podman(
                "build", *ULIMITS, *build_args, "-f", spec["build"]["dockerfile"],
                "-t", spec["image"], str(ROOT / spec["build"]["context"]), timeout_s=1200,
            )  # fmt: skip
            return time.monotonic() - started_s

    def run_arguments(self, service: str, container: str, **variables: str) -> list[str]:
        """`podman run` arguments for `service`: all compose.yaml says of it but `restart`."""
        spec = self.spec(service, **variables)
        args = ["--name", self.name(container), "--network", self.network]
        args += ["--network-alias", service, *ULIMITS]
        if spec.get("read_only"):
            args.append("--read-only")
        for path in spec.get("tmpfs", []):
            args += ["--tmpfs", path]
        for key, value in spec.get("environment", {}).items():
            args += ["-e", f"{key}={value}"]
        for volume in spec.get("volumes", []):
            source, target = volume.split(":", 1)
            if source.startswith(("/", ".")):  # a bind mount, relative to the compose file
                args += ["-v", f"{(ROOT / source).resolve()}:{target}"]
                continue
            assert source in self.compose["volumes"], f"{service}: {source} is no named volume"
            args += ["-v", f"{self.name(source)}:{target}"]
        for port in spec.get("ports", []):
            args += ["-p", port]
        if "healthcheck" in spec:
            check = spec["healthcheck"]
            assert check["test"][0] == "CMD", "health checks run without a shell"
            args += ["--health-cmd", json.dumps(check["test"][1:])]
            for option in ("interval", "timeout", "retries", "start_period"):
                if option in check:
                    args += [f"--health-{option.replace('_', '-')}", str(check[option])]
        if "entrypoint" in spec:
            entrypoint = spec["entrypoint"]
            words = shlex.split(entrypoint) if isinstance(entrypoint, str) else entrypoint
            args += ["--entrypoint", json.dumps(words)]
        return [*args, spec["image"], *spec.get("command", [])]

    def up(
        self, service: str, container: str | None = None, *, checked: bool = True, **variables: str
    ) -> str:
        """Start `service` detached (as `container`, by default the service's name) once
        what it depends on is started or healthy (`checked` False: the caller knows it is,
        and the start is not held up by health checks run again); the container's full
        name."""
        container = container or service
        for dependency, condition in self.spec(service).get("depends_on", {}).items():
            if checked and condition["condition"] == "service_healthy":
                self.wait_healthy(dependency)
        self.started_s[container] = time.monotonic()
        self.containers.append(self.name(container))
        podman("run", "-d", *self.run_arguments(service, container, **variables))
        return self.name(container)

    def up_services(self, services: Sequence[str]) -> dict[str, float]:
        """`services` started in order; seconds each with a health check took to turn healthy."""
        for service in services:
            self.up(service)
        return {
            service: round(self.wait_healthy(service), 1)
            for service in services
            if "healthcheck" in self.compose["services"][service]
        }

    def wait_healthy(self, container: str) -> float:
        """Run the container's health check until it passes (without systemd, Podman runs
        none by itself); seconds since the container was started."""
        deadline_s = time.monotonic() + HEALTHY_TIMEOUT_S
        while podman("healthcheck", "run", self.name(container), check=False).returncode != 0:
            assert self.inspect(container)["State"]["Running"], self.logs(container)
            assert time.monotonic() < deadline_s, f"{container} not healthy: {self.logs(container)}"
            time.sleep(0.5)
        return time.monotonic() - self.started_s[container]

    def health(self, container: str) -> str:
        state = self.inspect(container)["State"]
        return str((state.get("Health") or state.get("Healthcheck") or {}).get("Status"))

    def inspect(self, container: str) -> dict[str, Any]:
        return dict(json.loads(podman("inspect", self.name(container)).stdout)[0])

    def logs(self, container: str) -> str:
        run = podman("logs", self.name(container), check=False)
        return (run.stdout + run.stderr)[-4000:]

    def wait(self, container: str, timeout_s: float = 300) -> int:
        """Wait for the container to exit; its exit code."""
        run = podman("wait", self.name(container), timeout_s=timeout_s)
        return int(run.stdout.strip().splitlines()[-1])

    def volume(self, volume: str) -> Path:
        """Where a named volume's files are on this host."""
        run = podman("volume", "inspect", "--format", "{{.Mountpoint}}", self.name(volume))
        return Path(run.stdout.strip())

    def __enter__(self) -> Topology:
        self.__exit__()  # what a killed earlier run may have left
        podman("network", "create", self.network)
        for volume in self.compose["volumes"]:
            podman("volume", "create", self.name(volume))
        return self

    def __exit__(self, *exc: object) -> None:
        # One call each, which Podman runs side by side. Podman 4.3 removes nothing, and
        # says nothing, when one name of the call does not exist: `-i` skips the missing
        # containers, and the volumes are named only where they exist.
        names = {self.name(service) for service in self.compose["services"]}
        podman("rm", "-f", "-i", "-t", "2", *sorted(names | set(self.containers)), check=False)
        existing = set(podman("volume", "ls", "--format", "{{.Name}}").stdout.split())
        volumes = sorted(existing.intersection(map(self.name, self.compose["volumes"])))
        if volumes:
            podman("volume", "rm", "-f", *volumes, check=False)
        podman("network", "rm", "-f", self.network, check=False)


def acquired(out_dir: Path) -> list[dict[str, Any]]:
    """The scan log's acquisitions (empty before the log exists)."""
    path = out_dir / outputs.LOG_FILE
    lines = path.read_text().splitlines() if path.exists() else []
    return [entry for entry in map(json.loads, lines) if entry["event"] == "acquired"]
