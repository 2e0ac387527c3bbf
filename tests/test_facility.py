"""The facility topology, compose.facility.yaml, run with Podman: three scans at once while
an estimator replica and a Zenoh router die.

The test builds the images (the services' Dockerfiles; PostgreSQL and HAProxy from
Debian's packages on the same base, deploy/postgres and deploy/haproxy), runs PostgreSQL,
two estimator replicas behind HAProxy, two meshed routers and three scanners' instruments
and focus services as compose.facility.yaml describes them (compose_runner.py), waits for
their health checks, and starts the three schedulers, each on a slide of its own. Once
every scan is under way it kills estimator replica `estimator-a` with SIGKILL (it stays
dead: the scans go on through HAProxy on the other) and, once every scan has moved on,
router `zenoh-b` with SIGKILL, started again after ROUTER_DOWN_S as compose's restart
policy would (the test plays the orchestrator). Every scan must complete with every tile
in focus against the simulator's truth, and the database must hold exactly one event per
acquisition sequence of each slide, the same as each scan's log. Each scanner's focus
service reads its own scanner's slide only, so no scheduler is sent a focus result twice
(copies would be refused and counted in its report).

No registry can be reached here: everything runs from the base image that
compose_runner.py builds with debootstrap (PostgreSQL and HAProxy installed from the
Debian mirror in a layer of their own, cached by Podman like the services' layers), and
the routers are ours (ZENOH_IMAGE / ZENOH_ENTRYPOINT). The test needs root, Podman and
the Debian mirror (the first run only, for the base and the apt layers); elsewhere it
skips, saying what is missing. Figures (build times, time to healthy, each scan's wall
time, longest pause and in-focus rate) are printed as the test runs and written to
out/facility/report.json.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from compose_runner import Topology, acquired, ensure_base_image, ensure_engine, podman, say

from focustrack_core.testing import within
from focustrack_core.wire.session import free_port
from focustrack_estimator.event_store import open_store
from focustrack_scheduler import outputs

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1500)]

ROOT = Path(__file__).resolve().parents[1]
REPORT_DIR = ROOT / "out" / "facility"
ROWS = COLS = 6
SIZE = 256
SCANNERS = (1, 2, 3)
ESTIMATOR_TOKEN = "facility-estimator-token"
POSTGRES_PASSWORD = "facility-postgres-password"
AUTH = {"Authorization": f"Bearer {ESTIMATOR_TOKEN}"}
#: The long-running services, in an order that lets each start without waiting long for
#: another's health (each `up` waits for what it depends on): the schedulers are jobs.
SERVICES = (
    "postgres", "zenoh-a", "zenoh-b",
    "instrument-1", "instrument-2", "instrument-3", "focus-1", "focus-2", "focus-3",
    "estimator-a", "estimator-b", "estimator",
)  # fmt: skip
#: Acquisitions every scan has made before the replica is killed, and made since before
#: the router is killed.
KILL_AFTER = 6
ROUTER_DOWN_S = 5.0
#: Focus results a scan may refuse: a late one or two after the router's kill (a stack
#: asked for again while its first result was on its way). A focus service answering
#: every scanner's tiles would send each scan about two copies per acquisition.
LATE_RESULTS_ALLOWED = 3
SCAN_TIMEOUT_S = 600.0
FIGURES: dict[str, Any] = {}


def progress(config: pytest.Config, message: str) -> None:
    say(config, message, topic="facility")


def wait_for_balancer(
    http: httpx.Client, topology: Topology, url: str, timeout_s: float = 60.0
) -> None:
    """Until HAProxy answers a replica's /healthz (it checks the replicas every second)."""
    deadline_s = time.monotonic() + timeout_s
    while True:
        try:
            if http.get(f"{url}/healthz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        assert topology.inspect("estimator")["State"]["Running"], topology.logs("estimator")
        assert time.monotonic() < deadline_s, (
            f"HAProxy answers nothing: {topology.logs('estimator')}"
        )
        time.sleep(0.5)


@pytest.fixture(scope="module")
def facility(http: httpx.Client, pytestconfig: pytest.Config) -> Iterator[tuple[Topology, str]]:
    """The images built and every long-running service up and healthy; the topology and
    the estimators' URL (HAProxy, published on loopback)."""
    ensure_engine()
    base_image, FIGURES["base_image_s"] = ensure_base_image(pytestconfig)
    port = free_port()
    variables = {
        "FOCUSTRACK_VERSION": "e2e",
        "SLIDE_ROWS": str(ROWS),
        "SLIDE_COLS": str(COLS),
        "FRAME_SIZE": str(SIZE),
        "SERVE_TRUTH": "1",  # off by default: this test compares the scans with the truth
        "ESTIMATOR_PORT": f"127.0.0.1:{port}",
        "FOCUSTRACK_ESTIMATOR_TOKEN": ESTIMATOR_TOKEN,
        "POSTGRES_PASSWORD": POSTGRES_PASSWORD,
        # our router, from the instrument's image: the official one cannot be pulled here
        "ZENOH_IMAGE": "focustrack-instrument-sim:e2e",
        "ZENOH_ENTRYPOINT": "python3 -m focustrack_core.wire.router",
    }
    files = ("compose.facility.yaml",)
    with Topology(f"focustrack-facility-{os.getpid()}", variables, files) as running:
        builds_s: dict[str, float] = {}
        for service, spec in running.compose["services"].items():
            image = running.spec(service)["image"]
            if "build" in spec and image not in builds_s:  # one build per image
                progress(pytestconfig, f"building {image} on {base_image} ...")
                builds_s[image] = round(running.build(service, base_image), 1)
                progress(pytestconfig, f"built {image} in {builds_s[image]} s")
        FIGURES["build_s"] = builds_s
        started_s = time.monotonic()
        FIGURES["healthy_s"] = running.up_services(SERVICES)
        url = f"http://127.0.0.1:{port}"
        wait_for_balancer(http, running, url)
        FIGURES["all_healthy_s"] = round(time.monotonic() - started_s, 1)
        progress(pytestconfig, f"time to healthy (s): {FIGURES['healthy_s']}")
        yield running, url
        REPORT_DIR.mkdir(parents=True, exist_ok=True)
        (REPORT_DIR / "report.json").write_text(json.dumps(FIGURES, indent=2) + "\n")
        progress(pytestconfig, f"figures in {REPORT_DIR}/report.json")


class Scans:
    """The three schedulers' scans as they go: acquisitions logged, and the longest time
    each went from one acquisition to the next (sampled every POLL_S or so) in each
    `phase` of the test (a pause counts in the phase it ends in)."""

    POLL_S = 0.2

    def __init__(self, topology: Topology) -> None:
        self.topology = topology
        self.out_dirs = {n: topology.volume("scans") / f"scanner-{n}" for n in SCANNERS}
        self.counts = dict.fromkeys(SCANNERS, 0)
        self.last_s = dict.fromkeys(SCANNERS, time.monotonic())
        self.phase = "before the kills"
        self.longest_pause_s: dict[str, dict[int, float]] = {}

    def poll(self) -> None:
        now_s = time.monotonic()
        for n, out_dir in self.out_dirs.items():
            count = len(acquired(out_dir))
            if count > self.counts[n]:
                if self.counts[n] > 0:  # not the scan's start-up
                    pauses_s = self.longest_pause_s.setdefault(self.phase, {})
                    pauses_s[n] = round(max(pauses_s.get(n, 0.0), now_s - self.last_s[n]), 1)
                self.counts[n], self.last_s[n] = count, now_s

    def until(self, counts: dict[int, int], what: str) -> None:
        """Poll until every scan has logged at least `counts` acquisitions, or ended well
        (a scan far ahead of the others, on a loaded machine, may end before its count)."""
        deadline_s = time.monotonic() + SCAN_TIMEOUT_S
        ended_well: set[int] = set()
        while any(self.counts[n] < counts[n] for n in SCANNERS if n not in ended_well):
            for n in SCANNERS:
                container = f"scheduler-{n}"
                state = self.topology.inspect(container)["State"]
                if not state["Running"] and state["ExitCode"] == 0:
                    ended_well.add(n)
                ok = state["Running"] or n in ended_well or self.counts[n] >= counts[n]
                assert ok, self.topology.logs(container)
            assert time.monotonic() < deadline_s, f"no progress {what}: {self.counts}"
            time.sleep(self.POLL_S)
            self.poll()

    def running(self) -> bool:
        return any(self.topology.inspect(f"scheduler-{n}")["State"]["Running"] for n in SCANNERS)


def database_url(topology: Topology) -> str:
    """PostgreSQL on its container's address (reachable from this host, as root)."""
    networks = topology.inspect("postgres")["NetworkSettings"]["Networks"]
    address = networks[topology.network]["IPAddress"]
    return f"postgresql://focustrack:{POSTGRES_PASSWORD}@{address}:5432/focustrack"


def slide_state(http: httpx.Client, url: str) -> dict[str, Any]:
    """The slide's JSON through HAProxy, asked again while HAProxy answers 503 (up to 10 s):
    with one replica killed, the other is out for 2 s whenever it misses two health checks
    (`inter 1s fall 2`, each answered within `timeout check 3s`), which a machine loaded
    enough can still make it do."""
    answers: list[httpx.Response] = []

    def served() -> bool:
        answers.append(http.get(url, headers=AUTH))
        return answers[-1].status_code != 503

    within(served, timeout_s=10.0)
    answers[-1].raise_for_status()
    return dict(answers[-1].json())


def test_three_scans_at_once_ride_out_a_killed_replica_and_a_killed_router(
    http: httpx.Client, facility: tuple[Topology, str], pytestconfig: pytest.Config
) -> None:
    topology, estimator_url = facility
    started_s = time.monotonic()
    for n in SCANNERS:  # at once: what they depend on is healthy (the fixture saw to it)
        topology.up(f"scheduler-{n}", checked=False)
    scans = Scans(topology)
    scans.until(dict.fromkeys(SCANNERS, KILL_AFTER), "before the replica's kill")
    progress(pytestconfig, f"acquisitions {scans.counts}: SIGKILL estimator-a")
    podman("kill", "--signal", "KILL", topology.name("estimator-a"))
    scans.phase = "estimator-a killed"
    at_replica_kill = dict(scans.counts)
    scans.until({n: count + KILL_AFTER for n, count in at_replica_kill.items()}, "on one replica")
    progress(pytestconfig, f"acquisitions {scans.counts}: SIGKILL zenoh-b for {ROUTER_DOWN_S} s")
    podman("kill", "--signal", "KILL", topology.name("zenoh-b"))
    scans.phase = "zenoh-b killed"
    at_router_kill = dict(scans.counts)
    router_killed_s = time.monotonic()
    while time.monotonic() - router_killed_s < ROUTER_DOWN_S:
        time.sleep(Scans.POLL_S)
        scans.poll()
    podman("start", topology.name("zenoh-b"))
    progress(pytestconfig, f"acquisitions {scans.counts}: zenoh-b started again")
    deadline_s = time.monotonic() + SCAN_TIMEOUT_S
    while scans.running():
        assert time.monotonic() < deadline_s, f"scans not done: {scans.counts}"
        time.sleep(Scans.POLL_S)
        scans.poll()
    wall_s = time.monotonic() - started_s
    for n in SCANNERS:
        assert topology.wait(f"scheduler-{n}") == 0, topology.logs(f"scheduler-{n}")

    store = open_store(database_url(topology))
    figures: dict[str, Any] = {}
    try:
        for n, out_dir in scans.out_dirs.items():
            report = dict(json.loads((out_dir / outputs.REPORT).read_text()))
            slide_id = report["estimator_slide_id"]
            slide = slide_state(http, f"{estimator_url}/v1/slides/{slide_id}")
            logged = {entry["sequence"] for entry in acquired(out_dir)}
            stored = [event.sequence for event in store.events(slide_id)]
            figures[f"scanner-{n}"] = {
                "tiles_imaged": report["tiles_imaged"],
                "in_focus_fraction": report["in_focus_fraction"],
                "frames_per_tile": round(report["images_acquired"] / (ROWS * COLS), 2),
                "acquisitions": len(logged),
                "events_in_database": len(stored),
                "acquisitions_at_replica_kill": at_replica_kill[n],
                "acquisitions_at_router_kill": at_router_kill[n],
                "focus_results_rejected": report["focus_results_rejected"],
            }
            assert report["tiles_imaged"] == ROWS * COLS, n
            assert report["in_focus_fraction"] == 1.0, n  # every tile in focus: the truth's
            assert slide["done"] is True and slide["n_acquisitions"] == len(logged), n
            # one event per sequence, none lost and none twice, for every acquisition logged
            assert stored == list(range(slide["n_acquisitions"])), n
            assert logged == set(stored), n
            # one focus service per scanner: every tile answered once, not by all three
            assert report["focus_results_rejected"] <= LATE_RESULTS_ALLOWED, n
    finally:
        store.close()
    figures["wall_s"] = round(wall_s, 1)
    figures["longest_pause_s"] = scans.longest_pause_s
    FIGURES["scans"] = figures
    progress(pytestconfig, f"three scans: {figures}")
    assert not topology.inspect("estimator-a")["State"]["Running"]  # finished on the other
