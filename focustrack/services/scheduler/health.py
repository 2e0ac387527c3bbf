"""Health probes for container health checks (compose.yaml): exit 0 when the service answers.

python -m focustrack.services.scheduler.health --http http://127.0.0.1:8100/healthz
python -m focustrack.services.scheduler.health --instrument sim --connect tcp/zenoh:7447
"""

from __future__ import annotations

import argparse
import sys

import httpx
import zenoh

from focustrack.services.scheduler.clients import wait_for_instrument
from focustrack.wire import rpc
from focustrack.wire.session import open_session


def parser() -> argparse.ArgumentParser:
    probe = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    probe.add_argument("--http", metavar="URL", help="a /healthz URL that must answer 200")
    probe.add_argument("--instrument", metavar="NAME", help="an instrument that must answer")
    probe.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT")
    probe.add_argument("--timeout-s", type=float, default=5.0)
    return probe


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.http:
            response = httpx.get(args.http, timeout=args.timeout_s)
            response.raise_for_status()
        if args.instrument:
            with open_session(connect=args.connect, connect_timeout_s=args.timeout_s) as session:
                wait_for_instrument(session, args.instrument, args.timeout_s)
    except (httpx.HTTPError, rpc.RemoteError, zenoh.ZError, ValueError) as error:
        print(f"unhealthy: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
