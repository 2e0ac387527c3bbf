"""Open a Zenoh session for a service: endpoints from the command line, no multicast scouting.

Topology: one process listens (by default the instrument, an embedded peer on
``tcp/127.0.0.1:7447``, or a Zenoh router in deployments); the others connect to
it. A session that only connects runs in client mode, so the listener routes its
traffic: two peers that only connect would not see each other (checked with
zenoh 1.10), while clients do.

Shared memory (``--shared-memory MB``, off by default): the session accepts Zenoh
shared-memory buffers, and a publisher of pixels (`codec.PixelPublisher`) writes its
payloads into a pool of that many MB. Subscribers on the same host with it on then map
them without a copy; a link to a session that has it off, or to another host, carries
the bytes over the network instead, by itself. It is off by default: with it on, a
focus service killed mid-scan and restarted answered no stack in our end-to-end test
(zenoh 1.10, tests/test_scan_e2e.py; proto/README.md has what is known).

A Zenoh configuration file (``--zenoh-config FILE``, JSON5, Zenoh's own format) carries
what our options do not: TLS, user/password authentication, access control, tuning
(docs/security.md). Precedence: the file is read first, then our options are written
over it, always: the mode, the connect and listen endpoints (the flags', else the
command's defaults), multicast scouting (off), the connect timeout and retry, and
shared memory. So a file never changes where a service connects; the flags do. With
multicast scouting off, the scouting delay is 0 unless the file sets one: Zenoh's 500 ms
default held every router's open that long (zenoh 1.10; a peer's open did not wait).

Tuning for pixels (`PIXEL_TUNING`), written where the file leaves Zenoh's default:
Zenoh's transmit queue holds 2 batches of 64 KiB per priority and its receive pool
64 KiB per link, so a stack of 8 MB frames over TCP loopback waited on the round trip
and ran at about 1 GB/s, half a core idle. With 16 batches queued, a 16 MiB receive
pool and 8 MiB socket buffers the same frames run at 1.5-2.0 GB/s, copied out of Zenoh
included (`focustrack bench transport`, and bare sessions in two processes, zenoh 1.10;
16 is the most Zenoh accepts, 32 panics when a link opens). Memory: up to 16 MiB of
receive buffers per link while frames flow (about 3 MB per idle link).

`BackgroundSession` opens a session without blocking its caller and keeps trying
until the router answers, so a service starts before the router and connects when
it appears (its health says ``degraded`` meanwhile). Once open, a client session
reconnects to a restarted router by itself and declares its subscribers and
queryables again (checked with zenoh 1.10).
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import ClassVar, Literal, get_args

import zenoh
from pydantic import Field

from focustrack_core.serving import listening_socket
from focustrack_core.settings import ServiceSettings

log = logging.getLogger(__name__)

#: Where the embedded peer listens unless told otherwise.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

#: A session's Zenoh mode.
Mode = Literal["peer", "client", "router"]
MODES: tuple[str, ...] = get_args(Mode)

#: How long opening a session waits for a connect endpoint to come up.
CONNECT_TIMEOUT_S = 30.0

#: Zenoh's pauses between attempts to reach a connect endpoint that went away (ms): from
#: the first to the longest, doubling. An open session reconnects to a restarted router
#: within the longest pause of its return.
CONNECT_RETRY_MS = (250, 2000)

#: How long after its own session is back a `LinkWatch` gives the other services to be
#: back too (the longest connect retry pause, and half a second to declare their
#: subscribers again).
RECONNECT_GRACE_S = CONNECT_RETRY_MS[1] / 1000 + 0.5

#: How long one attempt of `BackgroundSession` waits for the router before the next.
ATTEMPT_TIMEOUT_S = 2.0

#: The longest pause between two attempts of `BackgroundSession` (it doubles up to this).
RETRY_MAX_S = 5.0

#: Zenoh settings that carry camera frames at speed (see the module's doc): key, value.
PIXEL_TUNING = {
    "transport/link/tx/queue/size/data": 16,  # batches of 64 KiB in flight per link
    "transport/link/rx/buffer_size": 16 * 1024 * 1024,  # bytes of receive buffers per link
    "transport/link/tcp/so_sndbuf": 8 * 1024 * 1024,  # bytes: the kernel's socket buffers
    "transport/link/tcp/so_rcvbuf": 8 * 1024 * 1024,
}

#: A good shared-memory pool for a pixel publisher, MB: 10 frames of 2048 x 2048 RGB uint16.
SHARED_MEMORY_MB = 256


#: The lowest port `free_port` picks.
LOWEST_FREE_PORT = 10000
#: How many of the ports it handed out last `free_port` never hands out again: a stack
#: picks each of its services' ports before any of them binds one.
RECENT_PORTS = 1000
_recent_ports: deque[int] = deque(maxlen=RECENT_PORTS)
_recent_ports_lock = threading.Lock()


def ephemeral_port_range() -> tuple[int, int]:
    """The ports the kernel gives outgoing connections (Linux's setting, else its default)."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for tests and embedded stacks).

    Picked at random below the kernel's ephemeral range: a port the kernel hands out (as
    binding port 0 does) may be given again as the source port of an outgoing connection
    (a Zenoh link, an HTTP request) before the server meant to listen there binds it,
    which failed a test now and then with "address already in use". Nor is a port this
    process was handed lately (`RECENT_PORTS`) handed out again: a port picked and not yet
    bound is free to the probe, and two services of one stack were once given the same.
    """
    low = ephemeral_port_range()[0]
    for _ in range(200):
        port = secrets.choice(range(LOWEST_FREE_PORT, low)) if low > LOWEST_FREE_PORT else 0
        with _recent_ports_lock, socket.socket() as probe:
            if port in _recent_ports:
                continue
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:  # taken: another
                continue
            port = int(probe.getsockname()[1])
            _recent_ports.append(port)
            return port
    raise OSError(f"no free port found between {LOWEST_FREE_PORT} and {low}")


def loopback_endpoint(port: int | None = None) -> str:
    """``tcp/127.0.0.1:PORT``, on a free port when `port` is None."""
    return f"tcp/127.0.0.1:{free_port() if port is None else port}"


def load_config_file(path: str | Path) -> zenoh.Config:
    """A Zenoh JSON5 configuration file; ValueError naming the file when it cannot be used."""
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as error:
        raise ValueError(f"Zenoh config {path}: {zenoh_message(error)}") from None


def zenoh_message(error: zenoh.ZError) -> str:
    """Zenoh's message without the path of the Rust source it came from."""
    return str(error).split(" at /", 1)[0]


def endpoint_parts(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of a Zenoh endpoint as written (`tcp/[::1]:7447?x#y` is
    ("tcp", "::1", "7447")); the port is the text after the last colon, checked by no one."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.split("?", 1)[0].split("#", 1)[0].rpartition(":")
    return protocol, host.strip("[]"), port


def check_port(flag: str, endpoint: str) -> None:
    """ValueError unless an IP endpoint's port (`tcp/127.0.0.1:7447`, `udp/[::1]:7447`) is a
    number from 0 to 65535. Zenoh takes `tcp/host:99999` and then fails at each attempt to
    connect or listen, which a service would retry for ever as a router that does not
    answer."""
    protocol, _, port = endpoint_parts(endpoint)
    if protocol not in ("tcp", "udp", "tls", "quic", "ws"):
        return
    if not (port.isascii() and port.isdigit() and int(port) <= 65535):
        raise ValueError(f"{flag} {endpoint}: the port must be a number from 0 to 65535")


def session_config(
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    mode: str | None = None,
    connect_timeout_s: float = CONNECT_TIMEOUT_S,
    shared_memory: bool = False,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config with these endpoints and multicast scouting off.

    `mode` defaults to "peer" when listening and "client" when only connecting.
    Opening keeps retrying the connect endpoints for `connect_timeout_s`, so
    services may start in any order. `shared_memory` lets the session exchange
    shared-memory buffers with peers on this host (off: every byte goes over the
    network, also from a peer that sends shared memory). `config_file` (Zenoh's
    JSON5) is the base that these options are written over (see the module's doc);
    `PIXEL_TUNING` applies where the file keeps Zenoh's default. ValueError, naming
    `--connect` or `--listen`, for an endpoint Zenoh cannot read or a port out of range.
    """
    if not connect and not listen:
        raise ValueError("a Zenoh session needs at least one --connect or --listen endpoint")
    mode = mode or ("peer" if listen else "client")
    if mode not in MODES:
        raise ValueError(f"unknown Zenoh mode {mode!r}; use one of {', '.join(MODES)}")
    config = zenoh.Config() if config_file is None else load_config_file(config_file)
    zenoh_defaults = zenoh.Config()
    for key, value in PIXEL_TUNING.items():
        if config.get_json(key) == zenoh_defaults.get_json(key):  # the file's own value wins
            config.insert_json5(key, json.dumps(value))
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    # With nothing to scout, a router still waited Zenoh's scouting delay (500 ms) at every
    # open, before it routed anything; a file's own delay is kept.
    if config.get_json("scouting/delay") == zenoh_defaults.get_json("scouting/delay"):
        config.insert_json5("scouting/delay", "0")
    for flag, key, endpoints in (
        ("--connect", "connect/endpoints", connect),
        ("--listen", "listen/endpoints", listen),
    ):
        for endpoint in endpoints:
            check_port(flag, endpoint)
        try:
            config.insert_json5(key, json.dumps(list(endpoints)))
        except zenoh.ZError as error:  # Zenoh's words, which name the endpoint
            reason = zenoh_message(error).split('msg: "', 1)[-1]
            raise ValueError(f"{flag}: {reason}") from error
    config.insert_json5("connect/timeout_ms", str(int(connect_timeout_s * 1000)))
    first_ms, longest_ms = CONNECT_RETRY_MS
    config.insert_json5(
        "connect/retry", f"{{period_init_ms: {first_ms}, period_max_ms: {longest_ms}}}"
    )
    config.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))
    return config


def open_config(
    config: zenoh.Config, on_wait: Callable[[], None] | None = None, patience_s: float = 2.0
) -> zenoh.Session:
    """`zenoh.open(config)`, with Ctrl-C heard while it waits for a connect endpoint, and
    `on_wait` called once when that wait has lasted `patience_s` (to say what it waits for:
    a wait of Zenoh's connect timeout, 30 s, in silence looks like a hang).

    Zenoh waits in native code, where Python runs no signal handler: a KeyboardInterrupt
    would wait for its connect timeout. It opens in a thread of its own while this one
    waits for it; an open that is interrupted is left to end there (a daemon thread: the
    process does not wait for it).
    """
    opened: Future[zenoh.Session] = Future()

    def open_in_thread() -> None:
        try:
            opened.set_result(zenoh.open(config))
        except BaseException as error:  # the caller's thread raises it
            opened.set_exception(error)

    threading.Thread(target=open_in_thread, name="zenoh-open", daemon=True).start()
    patience_ends_s = time.monotonic() + patience_s
    while True:
        try:
            return opened.result(timeout=0.1)
        except TimeoutError:
            if on_wait is not None and time.monotonic() >= patience_ends_s:
                on_wait()
                on_wait = None


def open_session(
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    mode: str | None = None,
    connect_timeout_s: float = CONNECT_TIMEOUT_S,
    shared_memory: bool = False,
    config_file: str | Path | None = None,
) -> zenoh.Session:
    """Open a session (see `session_config`); close it with `session.close()` or `with`.

    Raises zenoh.ZError when no connect endpoint answers within `connect_timeout_s`
    (or the router refuses the session: wrong credentials or certificates).
    """
    return open_config(
        session_config(connect, listen, mode, connect_timeout_s, shared_memory, config_file)
    )


class ZenohSettings(ServiceSettings):
    """The Zenoh options of every service on the bus (`ServiceSettings` subclasses add theirs).

    Neither ``--connect`` nor ``--listen`` given: the service's own endpoints
    (`default_connect`, `default_listen`), e.g. the instrument listens on
    `DEFAULT_ENDPOINT` and the others connect to it.
    """

    help_heading: ClassVar[str | None] = "zenoh"
    list_fields: ClassVar[tuple[str, ...]] = ("connect", "listen")
    default_connect: ClassVar[tuple[str, ...]] = ()
    default_listen: ClassVar[tuple[str, ...]] = ()

    connect: list[str] | None = Field(
        None,
        description=f"endpoints to connect to, e.g. {DEFAULT_ENDPOINT}",
        json_schema_extra={"metavar": "ENDPOINT"},
    )
    listen: list[str] | None = Field(
        None, description="endpoints to listen on", json_schema_extra={"metavar": "ENDPOINT"}
    )
    mode: Mode | None = Field(
        None, description="Zenoh mode (default: peer when listening, client when only connecting)"
    )
    zenoh_config: Path | None = Field(
        None,
        description="a Zenoh JSON5 configuration (TLS, user/password, access control; "
        "docs/security.md); the options above are written over it",
    )
    shared_memory: int = Field(
        0,
        ge=0,
        json_schema_extra={"metavar": "MB"},
        description="Zenoh shared memory with processes on this host: the pool, in MB, that "
        f"published pixels are written to, e.g. {SHARED_MEMORY_MB} (0: off, network only; "
        "subscribers need it on too, any size)",
    )

    @classmethod
    def default_text(cls, name: str) -> str | None:
        """--connect and --listen: the service's own endpoints when neither is given."""
        if name in ("connect", "listen"):
            endpoints = cls.default_connect if name == "connect" else cls.default_listen
            return " ".join(endpoints) or "none"
        return None

    def endpoints(self) -> tuple[list[str], list[str]]:
        """(connect, listen): the options', else the service's defaults."""
        if self.connect is None and self.listen is None:
            return list(self.default_connect), list(self.default_listen)
        return self.connect or [], self.listen or []

    @property
    def shared_memory_bytes(self) -> int:
        """The shared-memory pool of a pixel publisher, bytes (0: off)."""
        return self.shared_memory * 1_000_000

    def check_listen(self) -> None:
        """ListenError unless every TCP port this service is to listen on is free now. Zenoh
        fails at each attempt to listen on a port in use, which a service that waits for
        its bus would retry for ever, as "the Zenoh router does not answer"."""
        _, listen = self.endpoints()
        for endpoint in listen:
            protocol, host, port = endpoint_parts(endpoint)
            if protocol == "tcp" and port.isdigit() and int(port) > 0:
                listening_socket(host, int(port), f"Zenoh (--listen {endpoint})").close()

    def zenoh(self, connect_timeout_s: float = CONNECT_TIMEOUT_S) -> zenoh.Config:
        """The Zenoh config these options describe (ValueError if it cannot be used)."""
        connect, listen = self.endpoints()
        return session_config(
            connect,
            listen,
            self.mode,
            connect_timeout_s,
            shared_memory=self.shared_memory > 0,
            config_file=self.zenoh_config,
        )


class LinkWatch:
    """Whether a client session's link to the bus (its router, or the peer it connects to)
    went down since the watch began, and has been back for `grace_s`: what was in flight
    then is lost.

    Zenoh keeps nothing for a link that is gone, so a message published while the router
    was away (a focus result, the frames it would have come from) never arrives, and a
    wait for it can end once the bus is back rather than at its timeout. A watch begun
    while the session has no link counts that as the link down. A router that came back
    under the same id between two calls of `lost` goes unseen (the wait then runs to its
    timeout). Meant for client sessions, whose links all go to one node: a peer-mode
    session also counts any other peer that leaves.
    """

    def __init__(self, session: zenoh.Session, grace_s: float = RECONNECT_GRACE_S) -> None:
        self._session = session
        self._grace_s = grace_s
        self._links = self._connected()
        self._dropped = not self._links
        self._back_s: float | None = None
        self._fired = False

    def _connected(self) -> frozenset[str]:
        """The ids of the nodes the session has a link to."""
        info = self._session.info
        return frozenset(str(zid) for zid in (*info.routers_zid(), *info.peers_zid()))

    def lost(self) -> bool:
        """True once the link was down and has been up again for `grace_s` (and from then
        on, whatever the link does next)."""
        if self._fired:
            return True
        links = self._connected()
        self._dropped = self._dropped or not self._links <= links
        if not self._dropped or not links:
            self._back_s = None
            return False
        now_s = time.monotonic()
        if self._back_s is None:
            self._back_s = now_s
        self._fired = now_s - self._back_s >= self._grace_s
        return self._fired


class AliveTokens:
    """The liveliness tokens on `key_expr` alive now, as `session` sees them: a liveliness
    subscriber keeps the set, seeded with the tokens alive when it is made by a liveliness
    query (up to `seed_timeout_s`; the subscriber's history, which comes later, fills in
    what the query missed); close it when done.

    A token goes when its process undeclares it, closes its session or dies (its link
    closes, or its lease runs out where the link just goes silent).
    """

    def __init__(self, session: zenoh.Session, key_expr: str, seed_timeout_s: float = 2.0) -> None:
        self.key_expr = key_expr
        self._changed = threading.Condition()
        self._alive: set[str] = set()
        self._closed = False
        self._subscriber = session.liveliness().declare_subscriber(
            key_expr, handler=self._on_sample, history=True
        )
        for reply in session.liveliness().get(key_expr, timeout=seed_timeout_s):
            if reply.ok is not None:
                self._add(str(reply.ok.key_expr))

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._add(str(sample.key_expr))
        else:
            with self._changed:
                self._alive.discard(str(sample.key_expr))

    def _add(self, key_expr: str) -> None:
        with self._changed:
            self._alive.add(key_expr)
            self._changed.notify_all()

    def alive(self) -> frozenset[str]:
        with self._changed:
            return frozenset(self._alive)

    def wait_alive(self, timeout_s: float) -> bool:
        """Whether a token is alive, waiting up to `timeout_s` (s) for one to come."""
        with self._changed:
            return self._changed.wait_for(lambda: bool(self._alive), timeout_s)

    def close(self) -> None:
        """Undeclare the subscriber (once: closing again does nothing)."""
        if not self._closed:
            self._closed = True
            self._subscriber.undeclare()


class TokenWatch:
    """Whether every process whose token (`AliveTokens`) was alive when the watch began has
    gone (or none was) while another is alive now: what was asked of them is lost (a
    service that was not there missed it), and one that can do it again is there.

    While one of them is alive it may still publish, so the watch waits; a token that goes
    and comes back under the same key (its process's router restarted) is taken as never
    gone. A focus service declares its token once its subscription is declared, so a
    stack acquired again once `lost` says so reaches the one alive. Where no process
    declares a token (services that predate them) the watch never fires.
    """

    def __init__(self, tokens: AliveTokens) -> None:
        self._tokens = tokens
        self._started = tokens.alive()
        self._fired = False

    def lost(self) -> bool:
        """True once none of the tokens alive at the start is alive and another is (and
        from then on)."""
        if not self._fired:
            alive = self._tokens.alive()
            self._fired = bool(alive) and not self._started & alive
        return self._fired


class BackgroundSession:
    """A Zenoh session opened on a thread of its own, tried again until the router answers.

    `on_open(session)` runs once, on that thread, when the session is open (declare
    subscribers and queryables there). `health()` is ``degraded`` until then and while
    the session has no router or peer, ``ok`` otherwise. `make_config` is called for
    each attempt (opening uses a zenoh.Config up); give it a short connect timeout
    (`ATTEMPT_TIMEOUT_S`), so that `close` does not wait long.
    """

    def __init__(
        self,
        make_config: Callable[[], zenoh.Config],
        on_open: Callable[[zenoh.Session], None] = lambda _: None,
    ) -> None:
        self.session: zenoh.Session | None = None
        self.last_error = ""
        self._make_config = make_config
        self._on_open = on_open
        self._opened = threading.Event()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._open, name="zenoh-open", daemon=True)
        self._thread.start()

    def _open(self) -> None:
        pause_s = 0.25
        attempts = 0
        while not self._closing.is_set():
            attempts += 1
            try:
                session = zenoh.open(self._make_config())
            except zenoh.ZError as error:
                self.last_error = zenoh_message(error)
                if attempts == 1 or attempts % 10 == 0:
                    log.warning(
                        "the Zenoh router does not answer (attempt %d: %s); still trying",
                        attempts,
                        self.last_error,
                    )
                self._closing.wait(pause_s)
                pause_s = min(RETRY_MAX_S, 2 * pause_s)
                continue
            if self._closing.is_set():  # closed while this attempt was under way
                session.close()
                return
            self.session = session
            self._on_open(session)
            self._opened.set()
            log.info("Zenoh session open after %d attempt(s)", attempts)
            return

    def wait(self, timeout_s: float | None = None) -> zenoh.Session | None:
        """The session once it is open and ready; None after `timeout_s` or when closed."""
        self._opened.wait(timeout_s)
        return self.session if self._opened.is_set() else None

    def health(self) -> dict[str, str]:
        """``status`` ok, or degraded while not open or without a router or peer; ``zenoh``
        says which (for /healthz and logs)."""
        session = self.session if self._opened.is_set() else None
        if session is None:
            return {"status": "degraded", "zenoh": f"connecting: {self.last_error or '...'}"}
        info = session.info
        if not (info.routers_zid() or info.peers_zid()):
            return {"status": "degraded", "zenoh": "open, no router or peer reachable"}
        return {"status": "ok", "zenoh": "connected"}

    def close(self) -> None:
        self._closing.set()
        self._thread.join(ATTEMPT_TIMEOUT_S + 1.0)
        if self.session is not None:
            self.session.close()
            self.session = None


def shared_memory_room_mb(path: str | Path = "/dev/shm") -> int:
    """MB free for Zenoh's shared-memory pools (POSIX shared memory lives in /dev/shm), 0
    where there is none. A pool larger than this would crash its process with SIGBUS once
    its pages fill up (a container's /dev/shm is 64 MB unless told otherwise)."""
    try:
        stat = os.statvfs(path)
    except OSError:
        return 0
    return stat.f_bavail * stat.f_frsize // 1_000_000
