"""`focustrack serve estimator`: the estimator REST service under uvicorn.

    focustrack serve estimator --host 127.0.0.1 --port 8100 --store estimator.sqlite [--token T]

Every option may also come from the environment (`FOCUSTRACK_ESTIMATOR_<OPTION>`,
e.g. FOCUSTRACK_ESTIMATOR_TOKEN, which keeps the token out of the process list).
Without a token the API is open: bind it to loopback, or configure one.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from subprocess import DEVNULL, Popen

import httpx
import uvicorn

from focustrack_core.config import command_main
from focustrack_estimator.app import Settings, create_app


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    parser.add_argument("--port", type=int, default=8100, help="TCP port (default 8100)")
    parser.add_argument(
        "--store",
        default="estimator.sqlite",
        help="SQLite file holding every slide and its log (created if missing)",
    )
    parser.add_argument("--token", help="require this bearer token on /v1 (unset: no auth)")
    parser.add_argument(
        "--max-body-bytes", type=int, default=64 * 1024, help="largest request body accepted"
    )
    parser.add_argument(
        "--max-grid-side",
        type=int,
        default=Settings.max_grid_side,
        help="most tiles per side a slide's grid may have (larger: 422)",
    )
    parser.add_argument(
        "--max-grid-tiles",
        type=int,
        default=Settings.max_grid_tiles,
        help="most tiles a slide's grid may have (larger: 422)",
    )
    parser.add_argument(
        "--snapshot-every",
        type=int,
        default=Settings.snapshot_every,
        help="measurements between snapshots of a slide's state (a restart replays fewer)",
    )
    parser.add_argument("--access-log", action="store_true", help="log every request")


def run(args: argparse.Namespace) -> int:
    app = create_app(
        Settings(
            args.store,
            args.token or None,
            args.max_body_bytes,
            max_grid_side=args.max_grid_side,
            max_grid_tiles=args.max_grid_tiles,
            snapshot_every=args.snapshot_every,
        )
    )
    print(
        f"estimator on http://{args.host}:{args.port} (store {args.store}, "
        f"auth {'on' if args.token else 'off'})",
        flush=True,
    )
    try:
        uvicorn.run(
            app, host=args.host, port=args.port, log_level="warning", access_log=args.access_log
        )
    finally:
        app.state.slides.store.close()
    return 0


def spawn(store: str | Path, port: int, token: str | None = None, timeout_s: float = 60.0) -> Popen:
    """Start the service on 127.0.0.1:`port` as a child process; return once /healthz answers.

    For the end-to-end tests and `focustrack bench api`, which need the server in
    a process of its own (to kill it, or to keep its CPU apart from the client's).
    """
    env = dict(os.environ)
    if token:
        env[f"{ENV_PREFIX}TOKEN"] = token
    command = [sys.executable, "-m", "focustrack_estimator"]
    command += ["--port", str(port), "--store", str(store)]
    process = Popen(command, env=env, stdout=DEVNULL)
    deadline_s = time.monotonic() + timeout_s
    while time.monotonic() < deadline_s:
        if process.poll() is not None:
            raise RuntimeError(f"estimator exited with {process.returncode} before it was ready")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200:
                return process
        except httpx.TransportError:
            time.sleep(0.05)
    process.kill()
    raise RuntimeError(f"estimator did not answer on port {port} within {timeout_s} s")


#: Every option's environment variable is this prefix and its name (focustrack_core.config).
ENV_PREFIX = "FOCUSTRACK_ESTIMATOR_"

#: The `focustrack-estimator` console script (and `python -m focustrack_estimator`).
main = command_main(
    "focustrack-estimator", "the estimator REST service", add_arguments, run, ENV_PREFIX
)
