"""Containerized end to end: every image built, compose.yaml's topology run with Podman.

The test builds each service's image (services/*/Dockerfile), runs the `zenoh` router,
instrument, focus and estimator as compose.yaml describes them (the runner of
compose_runner.py reads compose.yaml: image, entry point, environment, volumes, tmpfs,
read-only root, health check, depends_on) on a Podman network of its own, waits for
each health check to pass, and runs the scheduler container to scan a 6x6 slide of
256 px tiles. The result must match the simulator's truth (every tile in focus) and the
same slide scanned by local processes (frames per tile). Then it kills the estimator container
mid-scan and starts it again; the scan must complete with nothing lost, since the
estimator's store lives on a volume. (The test plays the orchestrator: it does not pass
compose's `restart` policies, so the kill and the start are its own.) Last, the same
images run compose.secure.yaml merged over compose.yaml (as `compose -f ... -f ...`),
with the bus's secrets made as docs/security.md says: TLS, a login per role, the
router's access-control list and tagged focus results.

No registry can be reached here, so the base image is built from Debian's packages with
debootstrap (once per machine: it stays in Podman's store as BASE_TAG, with the host's
CA bundle for pip) and the `zenoh` service runs our router from the instrument's image
(ZENOH_IMAGE / ZENOH_ENTRYPOINT). Podman, runc and debootstrap are installed with
apt-get when missing and the test runs as root; elsewhere it skips, saying what is
missing. Layers are cached by Podman: a repeat run rebuilds only what changed (each
image installs its locked requirements in a layer of its own).

Figures (build times, time to healthy, in-focus rate, frames per tile in containers and
as processes, the restart check) are printed as the test runs and written to
out/containers/report.json.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from compose_runner import Topology, acquired, ensure_base_image, ensure_engine, podman, say

from focustrack.bus_secrets import restrict, write_bus_files
from focustrack.local_stack import LocalStack
from focustrack_core.wire.session import free_port
from focustrack_scheduler import outputs

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1500)]

ROOT = Path(__file__).resolve().parents[1]
REPORT_DIR = ROOT / "out" / "containers"
ROWS = COLS = 6
SIZE = 256
SEED = 5
STRATEGY = "kf-2d"  # compose.yaml's default
ESTIMATOR_TOKEN = "e2e-estimator-token"
#: The user every FocusTrack image runs as (services/*/Dockerfile).
CONTAINER_UID = 10001
AUTH = {"Authorization": f"Bearer {ESTIMATOR_TOKEN}"}
#: The long-running services, started in this order (the scheduler is a job).
SERVICES = ("zenoh", "instrument", "focus", "estimator")
FIGURES: dict[str, Any] = {}


# --- fixtures: the images, the running services, the same slide as local processes --------


def instrument_arguments() -> list[str]:
    return [
        "--seed", str(SEED), "--rows", str(ROWS), "--cols", str(COLS),
        "--width", str(SIZE), "--height", str(SIZE),
    ]  # fmt: skip


def write_report(out_dir: Path) -> None:
    """FIGURES as report.json, and as report.png: build and start times, then the scan's
    frames per tile in containers and as processes."""
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "report.json").write_text(json.dumps(FIGURES, indent=2) + "\n")
    figure, (times, scan) = plt.subplots(1, 2, figsize=(10, 4))
    for label, key in (("image build", "build_s"), ("to healthy", "healthy_s")):
        seconds = FIGURES.get(key, {})
        times.barh([f"{name}: {label}" for name in seconds], list(seconds.values()), label=label)
    times.legend()
    times.set_xlabel("s")
    times.set_title("images and services")
    runs = {"containers": FIGURES.get("scan", {}).get("frames_per_tile", 0.0)}
    runs["processes"] = FIGURES.get("scan", {}).get("local_frames_per_tile", 0.0)
    runs["containers, estimator killed"] = FIGURES.get("restart", {}).get("frames_per_tile", 0.0)
    scan.bar(list(runs), list(runs.values()), color=["C0", "C1", "C2"])
    scan.set_ylabel("frames per tile")
    scan.set_title(f"{ROWS}x{COLS} slide, {SIZE} px tiles")
    scan.tick_params(axis="x", labelsize=8)
    figure.tight_layout()
    figure.savefig(out_dir / "report.png", dpi=100)
    plt.close(figure)


@dataclass
class Stack:
    """The running topology and the estimator's REST API, published on loopback."""

    topology: Topology
    estimator_url: str


def topology_variables(estimator_port: int, focus_port: int) -> dict[str, str]:
    """What the tests' .env would say: the slide, the images, ports on loopback, tokens."""
    return {
        "FOCUSTRACK_VERSION": "e2e",
        "SLIDE_SEED": str(SEED),
        "SLIDE_ROWS": str(ROWS),
        "SLIDE_COLS": str(COLS),
        "FRAME_SIZE": str(SIZE),
        "SERVE_TRUTH": "1",  # off by default: this test compares the scan with the truth
        # published on loopback only: the test reads the estimator's REST API
        "ESTIMATOR_PORT": f"127.0.0.1:{estimator_port}",
        "FOCUS_PORT": f"127.0.0.1:{focus_port}",
        # the services' tokens, as .env sets them (without, they refuse to start)
        "FOCUSTRACK_ESTIMATOR_TOKEN": ESTIMATOR_TOKEN,
        "FOCUSTRACK_FOCUS_TOKEN": "e2e-focus-token",
        # our router, from the instrument's image: the official one cannot be pulled here
        "ZENOH_IMAGE": "focustrack-instrument-sim:e2e",
        "ZENOH_ENTRYPOINT": "python3 -m focustrack_core.wire.router",
    }


@pytest.fixture(scope="module")
def stack(pytestconfig: pytest.Config) -> Iterator[Stack]:
    """The images built and the router, instrument, focus and estimator up and healthy."""
    ensure_engine()
    base_image, FIGURES["base_image_s"] = ensure_base_image(pytestconfig)
    estimator_port, focus_port = free_port(), free_port()
    variables = topology_variables(estimator_port, focus_port)
    with Topology(f"focustrack-e2e-{os.getpid()}", variables) as running:
        builds_s = {}
        for service, spec in running.compose["services"].items():
            if "build" in spec:
                say(pytestconfig, f"building {service} on {base_image} ...")
                builds_s[service] = round(running.build(service, base_image), 1)
                say(pytestconfig, f"built {service} in {builds_s[service]} s")
        FIGURES["build_s"] = builds_s
        FIGURES["healthy_s"] = running.up_services(SERVICES)
        say(pytestconfig, f"time to healthy (s): {FIGURES['healthy_s']}")
        yield Stack(running, f"http://127.0.0.1:{estimator_port}")
        write_report(REPORT_DIR)
        say(pytestconfig, f"figures in {REPORT_DIR}/report.json and report.png")


@pytest.fixture(scope="module")
def secure_stack(
    stack: Stack, pytestconfig: pytest.Config, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Stack]:
    """compose.secure.yaml over compose.yaml, on the images `stack` built: the bus over TLS
    with a login per role, the router's access-control list, tagged focus results; the
    secrets as docs/security.md makes them (`focustrack bus secrets --owner 10001`)."""
    secrets_dir = tmp_path_factory.mktemp("bus") / "secrets"
    write_bus_files(secrets_dir, ["zenoh"], Path("/run/focustrack"))
    restrict(secrets_dir, CONTAINER_UID)
    estimator_port, focus_port = free_port(), free_port()
    variables = topology_variables(estimator_port, focus_port) | {"BUS_SECRETS": str(secrets_dir)}
    files = ("compose.yaml", "compose.secure.yaml")
    with Topology(f"focustrack-secure-{os.getpid()}", variables, files) as running:
        FIGURES["secure_healthy_s"] = running.up_services(SERVICES)
        say(pytestconfig, f"secure bus: time to healthy (s): {FIGURES['secure_healthy_s']}")
        yield Stack(running, f"http://127.0.0.1:{estimator_port}")


@pytest.fixture(scope="module")
def local_report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The same slide scanned by local processes (as in tests/test_scan_e2e.py): its report."""
    work = tmp_path_factory.mktemp("local")
    with LocalStack(work / "stack", instrument_arguments()) as local:
        scan = [
            sys.executable, "-m", "focustrack", "scan", "--no-progress",
            "--estimator", local.estimator_url, "--connect", local.endpoint,
            "--instrument", "sim", "--slide", "slide-0", "--strategy", STRATEGY,
            "--out", str(work / "scan"),
        ]  # fmt: skip
        run = subprocess.run(scan, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
    return dict(json.loads((work / "scan" / outputs.REPORT).read_text()))


# --- the tests -----------------------------------------------------------------------------


def complete_report(http: httpx.Client, stack: Stack, out_dir: Path) -> dict[str, Any]:
    """The scan's report, once it is checked complete: every tile imaged, the estimator's
    slide done, and every acquisition the estimator asked for in the scan's log."""
    report = dict(json.loads((out_dir / outputs.REPORT).read_text()))
    assert report["tiles_imaged"] == ROWS * COLS
    slide = http.get(
        f"{stack.estimator_url}/v1/slides/{report['estimator_slide_id']}", headers=AUTH
    ).json()
    assert slide["done"] is True
    assert {entry["sequence"] for entry in acquired(out_dir)} == set(range(slide["n_acquisitions"]))
    assert not (out_dir / outputs.PARTIAL_MOSAIC).exists()
    assert report["mosaic"] == outputs.MOSAIC_ZARR  # the default format
    assert (out_dir / outputs.MOSAIC_ZARR / "zarr.json").stat().st_size > 0
    return report


def test_services_turn_healthy_and_run_as_non_root_on_a_read_only_root(
    stack: Stack, pytestconfig: pytest.Config
) -> None:
    topology = stack.topology
    for service in ("zenoh", "instrument", "focus", "estimator"):
        info = topology.inspect(service)
        assert info["State"]["Running"], topology.logs(service)
        uid = podman("exec", topology.name(service), "id", "-u").stdout.strip()
        assert uid == "10001", f"{service} runs as uid {uid}"
        if service == "zenoh":
            assert "zenoh router listening on tcp/0.0.0.0:7447" in topology.logs(service)
            continue
        assert topology.health(service) == "healthy"
        assert info["HostConfig"]["ReadonlyRootfs"] is True
        write = podman("exec", topology.name(service), "touch", "/probe", check=False)
        assert write.returncode != 0 and "Read-only file system" in write.stderr
        podman("exec", topology.name(service), "touch", "/tmp/probe")  # the tmpfs is writable
    say(pytestconfig, "instrument, focus, estimator healthy; uid 10001; read-only root")


def test_a_scan_in_containers_matches_the_truth_and_the_same_scan_as_processes(
    http: httpx.Client, stack: Stack, local_report: dict[str, Any], pytestconfig: pytest.Config
) -> None:
    topology = stack.topology
    started_s = time.monotonic()
    scheduler = topology.up("scheduler", "scan-1", SCAN_NAME="scan-1")
    assert topology.wait("scan-1") == 0, topology.logs("scan-1")
    wall_s = time.monotonic() - started_s
    assert topology.inspect("scan-1")["Config"]["User"] == "focustrack", scheduler
    report = complete_report(http, stack, topology.volume("scans") / "scan-1")
    tiles = ROWS * COLS
    figures = {
        "in_focus_fraction": report["in_focus_fraction"],
        "local_in_focus_fraction": local_report["in_focus_fraction"],
        "frames_per_tile": report["images_acquired"] / tiles,
        "local_frames_per_tile": local_report["images_acquired"] / tiles,
        "mae_um": report["mae_um"],
        "local_mae_um": local_report["mae_um"],
        "scan_wall_s": round(wall_s, 1),
    }
    FIGURES["scan"] = figures
    say(pytestconfig, f"scan in containers vs processes: {figures}")
    assert report["in_focus_fraction"] == 1.0  # every tile within the depth of field
    assert local_report["in_focus_fraction"] == 1.0
    assert report["images_acquired"] == local_report["images_acquired"]


def test_a_scan_on_the_secure_bus_in_containers_logs_in_over_tls_and_trusts_its_results(
    http: httpx.Client,
    secure_stack: Stack,
    local_report: dict[str, Any],
    pytestconfig: pytest.Config,
) -> None:
    topology = secure_stack.topology
    assert "zenoh router listening on tls/0.0.0.0:7447" in topology.logs("zenoh")
    # the instrument turned healthy by its health check's own login (the health role)
    assert topology.health("instrument") == "healthy"
    topology.up("scheduler", "scan-secure", SCAN_NAME="scan-secure")
    assert topology.wait("scan-secure") == 0, topology.logs("scan-secure")
    report = complete_report(http, secure_stack, topology.volume("scans") / "scan-secure")
    figures = {
        "frames_per_tile": report["images_acquired"] / (ROWS * COLS),
        "local_frames_per_tile": local_report["images_acquired"] / (ROWS * COLS),
        "focus_results_rejected": report["focus_results_rejected"],
    }
    FIGURES["secure_scan"] = figures
    say(pytestconfig, f"scan on the secure bus: {figures}")
    # the same scan as processes on an open bus, frame for frame
    assert report["images_acquired"] == local_report["images_acquired"]
    assert report["focus_results_rejected"] == 0  # every result carried a valid tag
    # a secure deployment serves no truth (compose.secure.yaml): no in-focus figures
    assert report["in_focus_fraction"] is None


def test_the_estimator_killed_mid_scan_and_started_again_loses_nothing(
    http: httpx.Client, stack: Stack, pytestconfig: pytest.Config
) -> None:
    topology = stack.topology
    before = {
        slide["id"]: slide
        for slide in http.get(f"{stack.estimator_url}/v1/slides", headers=AUTH).json()
    }
    topology.up("scheduler", "scan-2", SCAN_NAME="scan-2")
    out_dir = topology.volume("scans") / "scan-2"
    deadline_s = time.monotonic() + 120
    while len(acquired(out_dir)) < 8:
        assert topology.inspect("scan-2")["State"]["Running"], topology.logs("scan-2")
        assert time.monotonic() < deadline_s, "the scan made no progress"
        time.sleep(0.05)
    podman("kill", topology.name("estimator"))
    killed_at = len(acquired(out_dir))
    time.sleep(2.0)
    assert topology.inspect("scan-2")["State"]["Running"]  # it waits for the estimator
    topology.started_s["estimator"] = time.monotonic()
    podman("start", topology.name("estimator"))
    healthy_again_s = topology.wait_healthy("estimator")
    assert topology.wait("scan-2") == 0, topology.logs("scan-2")
    report = complete_report(http, stack, out_dir)
    after = {
        slide["id"]: slide
        for slide in http.get(f"{stack.estimator_url}/v1/slides", headers=AUTH).json()
    }
    # Nothing lost: the slides from before the kill are all there, as they were, and the
    # interrupted scan's slide is complete.
    for slide_id, slide in before.items():
        assert after[slide_id]["n_acquisitions"] == slide["n_acquisitions"]
        assert after[slide_id]["done"] == slide["done"]
    figures = {
        "killed_after_acquisitions": killed_at,
        "estimator_healthy_again_s": round(healthy_again_s, 1),
        "tiles_imaged": report["tiles_imaged"],
        "in_focus_fraction": report["in_focus_fraction"],
        "frames_per_tile": report["images_acquired"] / (ROWS * COLS),
        "slides_kept": f"{len(set(before) & set(after))}/{len(before)}",
    }
    FIGURES["restart"] = figures
    say(pytestconfig, f"estimator killed mid-scan and started again: {figures}")
    assert report["in_focus_fraction"] == 1.0
