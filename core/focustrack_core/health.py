"""Health probes for container health checks: exit 0 when the service answers, 1 when not.

    python -m focustrack_core.health --http http://127.0.0.1:8100/healthz
    python -m focustrack_core.health --instrument sim --connect tcp/zenoh:7447
    python -m focustrack_core.health --instrument sim --connect tls/zenoh:7447 --zenoh-config F

`--http` needs nothing but the standard library (the estimator's image has no
Zenoh); `--instrument` asks the instrument's info queryable over Zenoh.
"""

from __future__ import annotations

import argparse
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the estimator's image has no Zenoh: imported where an instrument is probed
    import zenoh


def parser() -> argparse.ArgumentParser:
    probe = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    probe.add_argument("--http", metavar="URL", help="a /healthz URL that must answer 200")
    probe.add_argument("--instrument", metavar="NAME", help="an instrument that must answer")
    probe.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT")
    probe.add_argument(
        "--zenoh-config", type=Path, metavar="FILE", help="Zenoh JSON5 config (TLS, credentials)"
    )
    probe.add_argument("--timeout-s", type=float, default=5.0)
    return probe


def probe_http(url: str, timeout_s: float) -> None:
    """Return when `url` answers 2xx; raise OSError (or URLError) when it does not."""
    with urllib.request.urlopen(url, timeout=timeout_s) as response:
        if not 200 <= response.status < 300:
            raise OSError(f"{url} answered HTTP {response.status}")


def instrument_answers(session: zenoh.Session, name: str, timeout_s: float = 1.0) -> bool:
    """Whether instrument `name` answers its info query on `session` within `timeout_s`."""
    from focustrack_core.v1 import instrument_pb2
    from focustrack_core.wire import keys, rpc

    try:
        rpc.call(
            session,
            keys.info_key(name),
            instrument_pb2.AcquireRequest(),
            instrument_pb2.InstrumentInfo,
            timeout_s=timeout_s,
        )
    except rpc.RemoteError:
        return False
    return True


def probe_instrument(
    name: str, connect: list[str], timeout_s: float, config_file: Path | None = None
) -> None:
    """Return once instrument `name` answers its info query; raise TimeoutError if it does not."""
    from focustrack_core.wire.session import open_session

    deadline_s = time.monotonic() + timeout_s
    with open_session(
        connect=connect, connect_timeout_s=timeout_s, config_file=config_file
    ) as session:
        while not instrument_answers(session, name):
            if time.monotonic() > deadline_s:
                raise TimeoutError(f"instrument {name!r} did not answer within {timeout_s} s")
            time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.http:
            probe_http(args.http, args.timeout_s)
        if args.instrument:
            probe_instrument(args.instrument, args.connect, args.timeout_s, args.zenoh_config)
    except Exception as error:  # any failure is "unhealthy", with its reason
        print(f"unhealthy: {type(error).__name__}: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
