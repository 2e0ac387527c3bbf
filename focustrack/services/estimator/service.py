"""`focustrack serve estimator`: the estimator REST service under uvicorn.

    focustrack serve estimator --host 127.0.0.1 --port 8100 --store estimator.sqlite [--token T]

The token may also come from the environment (FOCUSTRACK_ESTIMATOR_TOKEN), which
keeps it out of the process list. Without a token the API is open: bind it to
loopback, or configure one.
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

from focustrack.services.estimator.app import Settings, create_app

TOKEN_ENV = "FOCUSTRACK_ESTIMATOR_TOKEN"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    parser.add_argument("--port", type=int, default=8100, help="TCP port (default 8100)")
    parser.add_argument(
        "--store",
        default="estimator.sqlite",
        help="SQLite file holding every slide and its log (created if missing)",
    )
    parser.add_argument(
        "--token",
        default=os.environ.get(TOKEN_ENV),
        help=f"require this bearer token on /v1 (default ${TOKEN_ENV}; unset: no auth)",
    )
    parser.add_argument(
        "--max-body-bytes", type=int, default=64 * 1024, help="largest request body accepted"
    )
    parser.add_argument("--access-log", action="store_true", help="log every request")


def run(args: argparse.Namespace) -> int:
    app = create_app(Settings(args.store, args.token or None, args.max_body_bytes))
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


def spawn(store: str | Path, port: int, token: str | None = None, timeout_s: float = 30.0) -> Popen:
    """Start the service on 127.0.0.1:`port` as a child process; return once /healthz answers.

    For the end-to-end tests and `focustrack bench api`, which need the server in
    a process of its own (to kill it, or to keep its CPU apart from the client's).
    """
    env = dict(os.environ)
    if token:
        env[TOKEN_ENV] = token
    command = [sys.executable, "-m", "focustrack", "serve", "estimator"]
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
