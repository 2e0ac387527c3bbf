"""A Zenoh router in one Python process, for deployments without the official router image.

    python3 -m focustrack_core.wire.router --listen tcp/0.0.0.0:7447 --no-multicast-scouting

It takes the official router's (zenohd's) flags that compose.yaml passes, so the
`zenoh` service keeps one command whichever image runs it: `--listen` (repeatable),
`--connect` (repeatable: other routers to mesh with, as compose.facility.yaml's two do;
each is tried again for as long as it is down) and `--no-multicast-scouting` (accepted
for that reason; multicast scouting is always off in our sessions), and `--config FILE`
(zenohd's name; `--zenoh-config` as our services call it, or
FOCUSTRACK_ROUTER_ZENOH_CONFIG): a Zenoh JSON5 file for TLS, user/password
authentication and access control (docs/security.md), which the endpoints and the mode
are written over. `--shared-memory` hands Zenoh shared-memory
buffers on between sessions on this host that have it on (`focustrack demo` with its
router in a process of its own); without it they cross the router as bytes, as between
hosts. It routes until SIGTERM or SIGINT, then
closes its session and exits 0: as a container's PID 1, a process without a SIGTERM
handler would ignore `stop` and be killed after the grace period.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

import zenoh

from focustrack_core.wire.session import session_config

#: The environment twin of --config (the one option a container sets: --listen is zenohd's
#: repeatable flag, which compose passes as it is).
CONFIG_ENV = "FOCUSTRACK_ROUTER_ZENOH_CONFIG"

#: The signals that stop the router.
STOP_SIGNALS = {signal.SIGTERM, signal.SIGINT}


def parser() -> argparse.ArgumentParser:
    router = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    router.add_argument(
        "-l",
        "--listen",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="an endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    router.add_argument(
        "-e",
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="another router to connect to, e.g. tcp/zenoh-a:7447 (repeatable): routers "
        "connected so route between their clients",
    )
    router.add_argument(
        "--no-multicast-scouting",
        action="store_true",
        help="accepted for zenohd compatibility; multicast scouting is always off",
    )
    router.add_argument(
        "--shared-memory",
        action="store_true",
        help="hand on Zenoh shared-memory buffers between sessions on this host "
        "(off: they cross this router as bytes)",
    )
    router.add_argument(
        "-c",
        "--config",
        "--zenoh-config",
        dest="zenoh_config",
        type=Path,
        default=os.environ.get(CONFIG_ENV) or None,
        metavar="FILE",
        help="a Zenoh JSON5 configuration: TLS, user/password, access control "
        f"(docs/security.md); --listen, --connect and the mode are written over it "
        f"[env {CONFIG_ENV}]",
    )
    return router


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        config = session_config(
            connect=args.connect,
            listen=args.listen,
            mode="router",
            shared_memory=args.shared_memory,
            config_file=args.zenoh_config,
        )
    except ValueError as error:  # a file Zenoh cannot use
        print(f"zenoh router: error: {error}", file=sys.stderr)
        return 2
    # Blocked before the session opens, so Zenoh's threads inherit the mask and the
    # signals wait for `sigwait` in this thread.
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as error:  # e.g. the endpoint is in use
        print(f"zenoh router: error: {error}", file=sys.stderr)
        return 2
    with session:
        print(f"zenoh router listening on {' '.join(args.listen)}", file=sys.stderr, flush=True)
        received = signal.sigwait(STOP_SIGNALS)
    print(f"zenoh router stopped by {signal.Signals(received).name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
