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


def probe_instrument(
    name: str, connect: list[str], timeout_s: float, config_file: Path | None = None
) -> None:
    """Return once instrument `name` answers its info query; raise RemoteError if it does not."""
    from focustrack_core.v1 import instrument_pb2
    from focustrack_core.wire import keys, rpc
    from focustrack_core.wire.session import open_session

    deadline_s = time.monotonic() + timeout_s
    with open_session(
        connect=connect, connect_timeout_s=timeout_s, config_file=config_file
    ) as session:
        while True:
            try:
                rpc.call(
                    session,
                    keys.info_key(name),
                    instrument_pb2.AcquireRequest(),
                    instrument_pb2.InstrumentInfo,
                    timeout_s=1.0,
                )
                return
            except rpc.RemoteError:
                if time.monotonic() > deadline_s:
                    raise
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
