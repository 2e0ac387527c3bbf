"""The authenticated bus: a Zenoh router with TLS, user/password and an access-control list.

The exploit: any Zenoh peer that reached the endpoint could command acquisitions,
read the ground truth and publish focus results. Here the router (ours, in its own
process) takes only TLS links, only users in its password file, and its ACL lets only
the scheduler query ``.../acquire`` and only the focus service publish results. A peer
without credentials is refused its session; a peer with a valid user but the wrong
role (``intruder``; and the focus service's own user, for acquisitions) gets no
answer and reaches no subscriber; the scan through it still completes. The
certificates, passwords and configs are made here with `focustrack bus secrets`'s
code (openssl), as for compose.secure.yaml; docs/security.md explains them.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import httpx
import pytest
import zenoh

from focustrack.bus_secrets import ROLES, client_config, write_bus_files
from focustrack.local_stack import Service
from focustrack_core.health import instrument_answers
from focustrack_core.testing import within
from focustrack_core.v1 import focus_pb2, instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_core.wire.session import AliveTokens, free_port, open_session

pytestmark = pytest.mark.slow  # real services in processes

INTRUDER = ("intruder", "pw-intruder")  # a valid user that no ACL rule names
#: The roles that declare a focus and a phase token each in the token test.
ROLES_TOKENS = ("intruder", "instrument", "focus", "phase", "scheduler", "health")


class Bus:
    """The secured router's endpoint and each role's config file."""

    def __init__(self, folder: Path) -> None:
        passwords = write_bus_files(folder, ["localhost"], extra_users=dict([INTRUDER]))
        self.endpoint = f"tls/localhost:{free_port()}"
        self.router_config = folder / "router.json5"
        self.configs = {role: folder / f"{role}.json5" for role in ROLES}
        for name, user, password in (
            ("intruder", *INTRUDER),
            ("anonymous", None, None),
            ("wrong-password", "scheduler", passwords["scheduler"] + "x"),
        ):
            self.configs[name] = folder / f"{name}.json5"
            config = client_config(folder / "ca.pem", user, password)
            self.configs[name].write_text(json.dumps(config))

    def open(self, role: str, timeout_s: float = 5.0) -> zenoh.Session:
        return open_session(
            connect=[self.endpoint], connect_timeout_s=timeout_s, config_file=self.configs[role]
        )


@pytest.fixture(scope="module")
def bus(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bus]:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is needed to make the test certificates")
    folder = tmp_path_factory.mktemp("bus")
    secured = Bus(folder)
    command = [sys.executable, "-m", "focustrack_core.wire.router", "--listen",
               secured.endpoint, "--zenoh-config", str(secured.router_config)]  # fmt: skip
    router = Service("router", command, folder / "router.log", lambda: _opens(secured))
    router.start()
    try:
        router.wait_ready(30)
        yield secured
    finally:
        router.stop()


def _opens(bus: Bus) -> bool:
    try:
        bus.open("scheduler", timeout_s=0.5).close()
        return True
    except zenoh.ZError:
        return False


@pytest.fixture(scope="module")
def stack(
    http: httpx.Client, bus: Bus, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[dict[str, str]]:
    """The instrument, focus and estimator services on the secured bus; their addresses."""
    folder = tmp_path_factory.mktemp("services")
    serve = [sys.executable, "-m", "focustrack", "serve"]
    estimator_port, focus_port = free_port(), free_port()
    estimator_url = f"http://127.0.0.1:{estimator_port}"

    def zenoh_args(role: str) -> list[str]:
        return ["--connect", bus.endpoint, "--zenoh-config", str(bus.configs[role])]

    with bus.open("scheduler") as probe:
        instrument = [*serve, "instrument", *zenoh_args("instrument"), "--name", "sim",
                      "--rows", "3", "--cols", "3", "--width", "64", "--height", "64"]  # fmt: skip
        focus = [*serve, "focus", *zenoh_args("focus"), "--port", str(focus_port)]
        store = ["--store", str(folder / "estimator.sqlite")]
        estimator = [*serve, "estimator", "--port", str(estimator_port), *store]
        services = [
            Service(
                "instrument",
                instrument,
                folder / "instrument.log",
                lambda: instrument_answers(probe, "sim"),
            ),
            Service(
                "focus",
                focus,
                folder / "focus.log",
                lambda: _http_ok(http, f"http://127.0.0.1:{focus_port}/healthz"),
            ),
            Service(
                "estimator",
                estimator,
                folder / "estimator.log",
                lambda: _http_ok(http, f"{estimator_url}/healthz"),
            ),
        ]
        for service in services:
            service.start()
        try:
            for service in services:
                service.wait_ready()
            yield {"estimator": estimator_url, "folder": str(folder)}
        finally:
            for service in services:
                service.stop()


def _http_ok(http: httpx.Client, url: str) -> bool:
    try:
        return http.get(url, timeout=1.0).status_code == 200
    except httpx.TransportError:
        return False


def test_a_peer_without_credentials_or_with_a_wrong_password_is_refused(bus: Bus) -> None:
    for role in ("anonymous", "wrong-password"):
        with pytest.raises(zenoh.ZError):
            bus.open(role, timeout_s=2.0).close()
    # A plain TCP link is not even listened for.
    with pytest.raises(zenoh.ZError):
        open_session(connect=[bus.endpoint.replace("tls/", "tcp/")], connect_timeout_s=2.0).close()


def test_only_the_scheduler_may_acquire_and_only_the_focus_service_publish_results(
    bus: Bus, stack: dict[str, str]
) -> None:
    request = instrument_pb2.AcquireRequest(
        slide="slide-0", row=0, col=0, z_low_um=-1.0, z_step_um=0.5, n_frames=3, sequence=7
    )
    for role in ("intruder", "focus", "health"):
        with bus.open(role) as session, pytest.raises(rpc.RemoteError) as refused:
            rpc.call(session, keys.acquire_key("sim"), request, instrument_pb2.AcquireReply, 3.0)
        assert refused.value.error.code in rpc.UNANSWERED  # nobody answers it
    with bus.open("health") as probe:  # the health checks' role may ask the info only
        info = rpc.call(probe, keys.info_key("sim"), instrument_pb2.AcquireRequest(),
                        instrument_pb2.InstrumentInfo, 5.0)  # fmt: skip
        assert info.instrument == "sim"
    with bus.open("scheduler") as scheduler:
        reply = rpc.call(
            scheduler, keys.acquire_key("sim"), request, instrument_pb2.AcquireReply, 30.0
        )
        assert list(reply.header.z_um) == [-1.0, -0.5, 0.0]
        # The ground truth is off unless asked for (and no role may ask for it here).
        with pytest.raises(rpc.RemoteError):
            rpc.call(scheduler, keys.truth_key("sim", "slide-0"),
                     instrument_pb2.AcquireRequest(), instrument_pb2.SlideTruth, 2.0)  # fmt: skip

        received: list[str] = []
        subscriber = scheduler.declare_subscriber(
            keys.focus_pattern("slide-0"),
            lambda sample: received.append(bytes(sample.payload.to_bytes()).decode()),
        )
        forged = focus_pb2.FocusResult(slide="slide-0", row=0, col=0, sequence=7, best_z_um=9.0)
        with bus.open("intruder") as intruder, bus.open("focus") as focus:
            time.sleep(1.0)  # let the subscriber's declaration reach both
            intruder.put(keys.focus_key("slide-0", 0, 0), b"intruder")
            focus.put(keys.focus_key("slide-0", 0, 0), b"focus")
            deadline_s = time.monotonic() + 10
            while "focus" not in received and time.monotonic() < deadline_s:
                time.sleep(0.05)
            intruder.put(keys.focus_key("slide-0", 0, 0), forged.SerializeToString())
            focus.put(keys.focus_key("slide-0", 0, 0), b"focus again")  # after the intruder's
            while "focus again" not in received and time.monotonic() < deadline_s:
                time.sleep(0.05)
        subscriber.undeclare()
    assert "focus" in received and "focus again" in received
    assert "intruder" not in received and len(received) == 2


def test_only_the_phase_service_publishes_phase_results_and_the_scheduler_reads_them(
    bus: Bus, stack: dict[str, str]
) -> None:
    received: list[str] = []
    with bus.open("scheduler") as scheduler:
        subscriber = scheduler.declare_subscriber(
            keys.phase_pattern("slide-0"),
            lambda sample: received.append(bytes(sample.payload.to_bytes()).decode()),
        )
        with bus.open("focus") as focus, bus.open("phase") as phase:
            time.sleep(1.0)  # let the subscriber's declaration reach both
            focus.put(keys.phase_key("slide-0", 0, 0), b"focus")
            phase.put(keys.phase_key("slide-0", 0, 0), b"phase")
            deadline_s = time.monotonic() + 10
            while "phase" not in received and time.monotonic() < deadline_s:
                time.sleep(0.05)
            phase.put(keys.focus_key("slide-0", 0, 0), b"phase as focus")  # not its key
            time.sleep(0.5)
        subscriber.undeclare()
    assert received == ["phase"]


def test_the_scheduler_sees_the_focus_and_phase_services_tokens_and_no_other_roles(
    bus: Bus, stack: dict[str, str]
) -> None:
    """A scan learns that a focus or phase service went from its liveliness token
    (`session.TokenWatch`): the ACL passes the tokens of those roles, on their own keys
    only, to the scheduler, and no other role's (a forged token would hold a lost
    result's wait open, or end it)."""
    with bus.open("scheduler") as scheduler:
        focus_services = AliveTokens(scheduler, keys.alive_pattern("focus", "slide-0"))
        phase_services = AliveTokens(scheduler, keys.alive_pattern("phase", "slide-0"))
        try:
            assert within(lambda: len(focus_services.alive()) == 1)  # the stack's service
            (served,) = focus_services.alive()
            with ExitStack() as sessions:
                roles = {role: sessions.enter_context(bus.open(role)) for role in ROLES_TOKENS}
                tokens = [
                    roles[role].liveliness().declare_token(keys.alive_key(service, "*", role))
                    for role in roles
                    for service in ("focus", "phase")
                ]  # held: a token undeclares itself once dropped
                assert within(lambda: len(phase_services.alive()) == 1)
                assert phase_services.alive() == {keys.alive_key("phase", "*", "phase")}
                time.sleep(0.5)  # the other roles' tokens, had they passed, would be there
                assert focus_services.alive() == {served, keys.alive_key("focus", "*", "focus")}
                assert phase_services.alive() == {keys.alive_key("phase", "*", "phase")}
                # A scheduler that starts now finds the same by its liveliness query. Zenoh
                # answers one empty now and then (2 runs in about 30 here), which AliveTokens
                # covers with its subscriber's history: asked again until it is answered.
                pattern = keys.alive_pattern("focus", "slide-0")

                def queried() -> set[str]:
                    replies = scheduler.liveliness().get(pattern, timeout=5.0)
                    return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

                assert within(lambda: queried() == focus_services.alive())
                del tokens
        finally:
            focus_services.close()
            phase_services.close()


def test_a_scan_through_the_secured_router_completes(
    bus: Bus, stack: dict[str, str], tmp_path: Path
) -> None:
    command = [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack["estimator"], "--connect", bus.endpoint,
        "--zenoh-config", str(bus.configs["scheduler"]),
        "--instrument", "sim", "--slide", "slide-0", "--strategy", "kf-2d",
        "--out", str(tmp_path / "scan"), "--instrument-outage-s", "20",
    ]  # fmt: skip
    scan = subprocess.run(command, capture_output=True, text=True, timeout=240)
    assert scan.returncode == 0, scan.stderr
    report = json.loads((tmp_path / "scan" / "report.json").read_text())
    assert report["tiles_imaged"] == 9
    assert report["in_focus_fraction"] is None  # no truth on this bus
