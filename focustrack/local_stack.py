"""The embedded stack: a Zenoh router and the services on loopback, each a real process.

`LocalStack` is what `focustrack demo`, the benches that scan through the services
(`focustrack bench slide`, `chaos`, `mmcore`) and the end-to-end tests run: no router or
database to install, every service started with `python -m focustrack serve ...`, its
output in a log file of the stack's folder, and stopped on the way out.
"""

from __future__ import annotations

import ctypes
import os
import secrets
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from subprocess import STDOUT, Popen, TimeoutExpired

import httpx
import zenoh

from focustrack_core.wire import rpc
from focustrack_core.wire.session import free_port, loopback_endpoint, open_session
from focustrack_core.wire.trust import ResultSigner
from focustrack_scheduler.clients import wait_for_instrument

#: The name the stack's instrument serves under, and its first slide.
INSTRUMENT = "sim"
SLIDE = "slide-0"
#: Seconds a service may take to answer once started.
READY_TIMEOUT_S = 60.0
#: How often the stack looks for a service that died.
SUPERVISE_PERIOD_S = 0.5


@dataclass
class Service:
    """A service in a process of its own; its output goes to `log_path`."""

    name: str
    command: list[str]
    log_path: Path
    ready: Callable[[], bool]
    process: Popen | None = field(default=None, repr=False)

    def died(self) -> int | None:
        """The exit status of a process that ended (None while it runs or was never started)."""
        return None if self.process is None else self.process.poll()

    def start(self) -> None:
        with self.log_path.open("a") as log_file:
            # A session of its own: Ctrl-C reaches the demo only, which stops this cleanly.
            self.process = Popen(
                self.command,
                stdout=log_file,
                stderr=STDOUT,
                start_new_session=True,
                preexec_fn=_ended_with(os.getpid()),
            )

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        deadline_s = time.monotonic() + timeout_s
        while not self.ready():
            assert self.process is not None
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"{self.name} exited with status {self.process.returncode}; see {self.log_path}"
                )
            if time.monotonic() > deadline_s:
                raise RuntimeError(f"{self.name} not ready after {timeout_s:.0f} s")
            time.sleep(0.2)

    def kill(self) -> None:
        """SIGKILL, as a crash would."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM, then SIGKILL if it has not ended within `timeout_s`."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.terminate()
        try:
            self.process.wait(timeout_s)
        except TimeoutExpired:
            self.kill()


#: prctl's option that sends the calling process a signal when its parent ends (Linux).
_PR_SET_PDEATHSIG = 1


def _ended_with(parent_pid: int) -> Callable[[], None] | None:
    """What a child runs before it starts its command so that it is sent SIGTERM when the
    stack's process ends, even by SIGKILL, which no `finally` hears (services used to
    outlive a killed demo or bench, holding their ports); None where there is no prctl.

    Linux sends the signal when the *thread* that started the child ends, so only children
    started on the main thread are given it: a service restarted by a thread of its own
    (the stack's supervisor, `bench chaos`'s faults) would be stopped when that thread ends.
    """
    if not sys.platform.startswith("linux") or threading.current_thread() is not (
        threading.main_thread()
    ):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here, not in the child

    def set_parent_death_signal() -> None:
        prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:  # the parent ended before the line above
            os.kill(os.getpid(), signal.SIGTERM)

    return set_parent_death_signal


def _tcp_ready(port: int) -> Callable[[], bool]:
    def ready() -> bool:
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", port)) == 0

    return ready


def _http_ready(http: httpx.Client, port: int, *, linked: bool = False) -> Callable[[], bool]:
    """Ready when ``/healthz`` answers (with `linked`: and says its Zenoh session is up),
    asked with `http`: one client for every probe, since an httpx client costs about 50 ms
    of CPU to make (its TLS context: the CA bundle read and parsed), which a probe every
    0.2 s would spend while the service it waits for starts on the same cores."""

    def ready() -> bool:
        try:
            answer = http.get(f"http://127.0.0.1:{port}/healthz")
        except httpx.TransportError:
            return False
        return answer.status_code == 200 and (not linked or answer.json()["status"] == "ok")

    return ready


def _new_key(path: Path) -> Path:
    """`path`, a new random key file (32 bytes in hex) for its owner alone."""
    path.write_text(secrets.token_hex(32) + "\n")
    path.chmod(0o600)
    return path


class LocalStack:
    """A Zenoh router and the three services on loopback, as a context manager.

    `instrument_args` are extra options of `focustrack serve instrument` (slides, frames),
    `focus_args` of `focustrack serve focus` (a focus mode).
    The router runs in this process, or with `router_process` in one of its own (so it
    can be killed and started again: `services["router"]`). With `supervise`, a service
    that dies is started again, and a line on stderr says so. The instrument serves its
    truth (evaluation; not with `serve_truth` False, for an instrument that has none) and
    tags its frames with the key in `frame_key_file`, which the focus service checks; the
    focus service tags its results with `trust`'s key. With
    `shared_memory_mb`, the instrument publishes its frames into a shared-memory pool of
    that size, and every session of the stack takes them from there.
    """

    def __init__(
        self,
        work_dir: Path,
        instrument_args: list[str],
        *,
        router_process: bool = False,
        supervise: bool = False,
        shared_memory_mb: int = 0,
        serve_truth: bool = True,
        phase: bool = False,
        focus_args: tuple[str, ...] = (),
    ) -> None:
        self.work_dir = Path(work_dir)
        (self.work_dir / "logs").mkdir(parents=True, exist_ok=True)
        self.endpoint = loopback_endpoint()
        self.estimator_port = free_port()
        self.estimator_url = f"http://127.0.0.1:{self.estimator_port}"
        self.store = self.work_dir / "estimator.sqlite"
        self.result_key_file = _new_key(self.work_dir / "result.key")
        self.frame_key_file = _new_key(self.work_dir / "frame.key")
        self.trust = ResultSigner.from_file(self.result_key_file)
        self.session: zenoh.Session | None = None
        self._http = httpx.Client(timeout=1.0)  # the services' readiness probes (thread-safe)
        self.focus_port = free_port()
        serve = [sys.executable, "-m", "focustrack", "serve"]
        connect = ["--connect", self.endpoint]
        self.shared_memory = shared_memory_mb > 0
        if self.shared_memory:
            connect += ["--shared-memory", str(shared_memory_mb)]
        store = ["--store", str(self.store)]
        logs = self.work_dir / "logs"
        self.services: dict[str, Service] = {}
        self.router_process = router_process
        if router_process:
            port = int(self.endpoint.rsplit(":", 1)[1])
            router = [
                sys.executable,
                "-m",
                "focustrack_core.wire.router",
                "--listen",
                self.endpoint,
            ]
            if self.shared_memory:
                router.append("--shared-memory")
            self.services["router"] = Service(
                "router", router, logs / "router.log", _tcp_ready(port)
            )
        frame_key = ["--frame-key-file", str(self.frame_key_file)]
        instrument = [*serve, "instrument", *connect, "--name", INSTRUMENT]
        if serve_truth:
            instrument.append("--serve-truth")
        focus = [*serve, "focus", *connect, "--result-key-file", str(self.result_key_file)]
        self.services |= {
            "instrument": Service(
                "instrument",
                [*instrument, *frame_key, *instrument_args],
                logs / "instrument.log",
                self._instrument_ready,
            ),
            "focus": Service(
                "focus",
                [*focus, *frame_key, "--port", str(self.focus_port), *focus_args],
                logs / "focus.log",
                _http_ready(self._http, self.focus_port),
            ),
            "estimator": Service(
                "estimator",
                [*serve, "estimator", "--port", str(self.estimator_port), *store],
                logs / "estimator.log",
                _http_ready(self._http, self.estimator_port),
            ),
        }
        if phase:
            phase_port = free_port()
            keys = ["--result-key-file", str(self.result_key_file), *frame_key]
            self.services["phase"] = Service(
                "phase",
                [*serve, "phase", *connect, *keys, "--port", str(phase_port)],
                logs / "phase.log",
                _http_ready(self._http, phase_port, linked=True),
            )
        self.supervise = supervise
        self.restarts: dict[str, int] = dict.fromkeys(self.services, 0)
        self._closing = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._held: set[str] = set()  # services being replaced: not the supervisor's to start
        self._lock = threading.Lock()

    def _instrument_ready(self) -> bool:
        assert self.session is not None
        try:
            wait_for_instrument(self.session, INSTRUMENT, timeout_s=0.0)
            return True
        except rpc.RemoteError:
            return False

    def __enter__(self) -> LocalStack:
        try:
            if self.router_process:
                router = self.services["router"]
                router.start()
                router.wait_ready()
                self.session = open_session(
                    connect=[self.endpoint], shared_memory=self.shared_memory
                )
            else:
                self.session = open_session(
                    listen=[self.endpoint], mode="router", shared_memory=self.shared_memory
                )
            for service in self.services.values():
                if service.process is None:
                    service.start()
            for service in self.services.values():
                service.wait_ready()
        except BaseException:
            self.close()
            raise
        if self.supervise:
            self._supervisor = threading.Thread(
                target=self._watch, name="stack-supervisor", daemon=True
            )
            self._supervisor.start()
        return self

    def _watch(self) -> None:
        """Start again every service that died, saying so (until the stack closes)."""
        while not self._closing.wait(SUPERVISE_PERIOD_S):
            for name, service in self.services.items():
                with self._lock:
                    status = None if name in self._held else service.died()
                    if status is None or self._closing.is_set():
                        continue
                    self.restarts[name] += 1
                    print(
                        f"focustrack stack: {name} exited with status {status}; starting it "
                        f"again (restart {self.restarts[name]}, log {service.log_path})",
                        file=sys.stderr,
                        flush=True,
                    )
                    service.start()

    def restart(self, name: str) -> None:
        """Start service `name` again (after `kill` or `stop`) and wait until it answers."""
        service = self.services[name]
        service.start()
        service.wait_ready()

    def restart_with(self, name: str, extra_args: list[str]) -> None:
        """Stop service `name`, start it again with `extra_args` added to its command, and
        wait until it answers; the supervisor leaves it alone meanwhile."""
        with self._lock:
            self._held.add(name)
        try:
            service = self.services[name]
            service.stop()
            service.command = [*service.command, *extra_args]
            self.restart(name)
        finally:
            with self._lock:
                self._held.discard(name)

    def close(self) -> None:
        self._closing.set()
        if self._supervisor is not None:
            self._supervisor.join()
        for service in reversed(self.services.values()):
            if service.name != "router":
                service.stop()
        if self.session is not None:
            self.session.close()
            self.session = None
        if "router" in self.services:
            self.services["router"].stop()
        self._http.close()

    def __exit__(self, *_: object) -> None:
        self.close()


def stop_on_sigterm() -> None:
    """SIGTERM raises KeyboardInterrupt, so that `with LocalStack(...)` stops the services."""

    def interrupt(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
