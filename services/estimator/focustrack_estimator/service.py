"""`focustrack serve estimator`: the estimator REST service under uvicorn.

    focustrack serve estimator --host 127.0.0.1 --port 8100 --store estimator.sqlite [--token T]

Every option may also come from the environment (`FOCUSTRACK_ESTIMATOR_<OPTION>`,
e.g. FOCUSTRACK_ESTIMATOR_TOKEN, which keeps the token out of the process list).
Without a token the API is open: off loopback the service refuses to start without
one unless --insecure is given. The store is checked at start (a damaged file: exit
code 2 and a message naming it); SIGTERM, like Ctrl-C, snapshots the live slides,
checkpoints and closes the store, and exits 0.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from subprocess import DEVNULL, Popen

import httpx
import uvicorn

from focustrack_core.config import command_main
from focustrack_core.serving import refuse_open_network
from focustrack_estimator import registry
from focustrack_estimator.app import Settings, create_app
from focustrack_estimator.store import StoreError


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
        "--insecure",
        action="store_true",
        help="serve without a token on a non-loopback address (refused otherwise)",
    )
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
    parser.add_argument(
        "--body-timeout-s",
        type=float,
        default=Settings.body_timeout_s,
        help="seconds a request body may take to arrive (slower: 408)",
    )
    parser.add_argument(
        "--max-slide-bytes",
        type=int,
        default=Settings.max_slide_bytes,
        help="largest projected memory of one slide, bytes (more: 422 at creation)",
    )
    parser.add_argument(
        "--max-tile-seconds",
        type=float,
        default=Settings.max_tile_s,
        help="largest projected computation per tile of a slide, seconds (more: 422)",
    )
    parser.add_argument(
        "--max-live-slides",
        type=int,
        default=Settings.max_live_slides,
        help="slides kept in memory; the least recently used beyond are evicted (reloaded "
        "from the store on their next request)",
    )
    parser.add_argument(
        "--max-live-bytes",
        type=int,
        default=Settings.max_live_bytes,
        help="projected bytes the slides in memory may hold together (beyond: evicted)",
    )
    parser.add_argument(
        "--strategies-from",
        metavar="MODULE",
        help="serve the strategies of MODULE's CATALOGUE instead of the estimator's own "
        "(opt-in: focustrack.bench.strategies adds gp-oracle, the benchmarks' floor)",
    )
    parser.add_argument("--access-log", action="store_true", help="log every request")


def catalogue_from(module_name: str | None) -> registry.Catalogue:
    """The served strategies: the estimator's, or `module_name`'s CATALOGUE (ValueError)."""
    if not module_name:
        return registry.SERVED
    try:
        catalogue = importlib.import_module(module_name).CATALOGUE
    except (ImportError, AttributeError) as error:
        raise ValueError(f"--strategies-from {module_name}: no CATALOGUE there ({error})") from None
    if not isinstance(catalogue, registry.Catalogue):
        raise ValueError(f"--strategies-from {module_name}: CATALOGUE is not a registry.Catalogue")
    return catalogue


def run(args: argparse.Namespace) -> int:
    refusal = refuse_open_network("estimator", args.host, args.token, args.insecure)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    try:
        app = create_app(
            Settings(
                args.store,
                args.token or None,
                args.max_body_bytes,
                max_grid_side=args.max_grid_side,
                max_grid_tiles=args.max_grid_tiles,
                snapshot_every=args.snapshot_every,
                body_timeout_s=args.body_timeout_s,
                max_slide_bytes=args.max_slide_bytes,
                max_tile_s=args.max_tile_seconds,
                max_live_slides=args.max_live_slides,
                max_live_bytes=args.max_live_bytes,
                catalogue=catalogue_from(args.strategies_from),
            )
        )
    except (StoreError, ValueError) as error:
        print(f"estimator not started: {error}", file=sys.stderr)
        return 2
    store = app.state.slides.store
    if store.created:
        print(f"creating a new store at {args.store} (the file was missing or empty)", flush=True)
    print(
        f"estimator on http://{args.host}:{args.port} (store {args.store}, "
        f"auth {'on' if args.token else 'off'})",
        flush=True,
    )
    # uvicorn shuts down gracefully on SIGTERM and then raises the signal again, which
    # with the default handler kills the process (-15) before the store is closed and its
    # WAL checkpointed: this handler takes that second delivery, so `finally` runs.
    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    try:
        uvicorn.run(
            app, host=args.host, port=args.port, log_level="warning", access_log=args.access_log
        )
    finally:
        store.close()
        signal.signal(signal.SIGTERM, previous)
    return 0


def spawn(
    store: str | Path,
    port: int,
    token: str | None = None,
    timeout_s: float = 60.0,
    options: Sequence[str] = (),
) -> Popen:
    """Start the service on 127.0.0.1:`port` as a child process; return once /healthz answers.

    For the end-to-end tests and `focustrack bench api`, which need the server in
    a process of its own (to kill it, or to keep its CPU apart from the client's).
    `options`: more of the command's flags (`--max-live-slides`, `2`, ...).
    """
    env = dict(os.environ)
    if token:
        env[f"{ENV_PREFIX}TOKEN"] = token
    command = [sys.executable, "-m", "focustrack_estimator"]
    command += ["--port", str(port), "--store", str(store), *options]
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
