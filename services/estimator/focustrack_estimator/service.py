"""`focustrack serve estimator`: the estimator REST service under uvicorn.

    focustrack serve estimator --host 127.0.0.1 --port 8100 --store estimator.sqlite [--token T]

Every option may also come from the environment (`FOCUSTRACK_ESTIMATOR_<OPTION>`,
e.g. FOCUSTRACK_ESTIMATOR_TOKEN, which keeps the token out of the process list) or
a settings file (`EstimatorSettings`). Without a token the API is open: off loopback
the service refuses to start without one unless --insecure is given. The store is
checked at start (a damaged file: exit code 2 and a message naming it); SIGTERM,
like Ctrl-C, snapshots the live slides, checkpoints and closes the store, and exits 0.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from subprocess import DEVNULL, Popen
from typing import TYPE_CHECKING

from focustrack_core import tracing
from focustrack_core.serving import (
    ListenError,
    http_url,
    listening_socket,
    refuse_open_network,
    serve_until_stopped,
)
from focustrack_core.settings import command_main
from focustrack_estimator.app import create_app
from focustrack_estimator.event_store import EventStore, StoreError, open_store
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.sqlite_store import SQLiteStore

if TYPE_CHECKING:
    from focustrack_estimator.registry import Catalogue

#: The settings model `focustrack serve estimator` reads (flags, environment, file).
Settings = EstimatorSettings


def catalogue_from(module_name: str) -> Catalogue:
    """The strategies of `module_name`'s CATALOGUE (ValueError if it has none)."""
    # Imported here, not with the service: the estimator's own strategies load on first use.
    from focustrack_estimator.registry import Catalogue

    try:
        catalogue = importlib.import_module(module_name).CATALOGUE
    except (ImportError, AttributeError) as error:
        raise ValueError(f"--strategies-from {module_name}: no CATALOGUE there ({error})") from None
    if not isinstance(catalogue, Catalogue):
        raise ValueError(f"--strategies-from {module_name}: CATALOGUE is not a registry.Catalogue")
    return catalogue


def new_store_note(store: EventStore) -> str:
    """What the service says at start of a store it has just made (no password in it)."""
    if isinstance(store, SQLiteStore):
        return f"creating a new store at {store.address} (the file was missing or empty)"
    return f"created the estimator's tables in {store.address} (the database had none)"


def run(settings: EstimatorSettings) -> int:
    refusal = refuse_open_network("estimator", settings.host, settings.token, settings.insecure)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    try:
        catalogue = None
        if settings.strategies_from is not None:
            catalogue = catalogue_from(settings.strategies_from)
        listening = listening_socket(settings.host, settings.port, "estimator")
    except (ListenError, ValueError) as error:
        print(f"estimator not started: {error}", file=sys.stderr)
        return 2
    try:
        # last: a bad setting touches no file
        store = open_store(settings.store, settings.store_timeout_s)
    except StoreError as error:
        listening.close()
        print(f"estimator not started: {error}", file=sys.stderr)
        return 2
    if store.created:
        print(new_store_note(store), flush=True)
    traced = tracing.configure("focustrack-estimator", settings.otlp_endpoint)
    port = listening.getsockname()[1]  # --port 0: the one the system chose
    print(
        f"estimator on {http_url(settings.host, port)} (store {store.address}, "
        f"auth {'on' if settings.token else 'off'}, traces {'on' if traced else 'off'})",
        flush=True,
    )
    try:  # until SIGINT or SIGTERM; then the store is closed and its WAL checkpointed
        serve_until_stopped(
            create_app(store, settings, catalogue),
            listening,
            log_level="warning",
            access_log=settings.access_log,
            ws="none",  # no WebSocket routes: importing a WebSocket library would slow the start
        )
    finally:
        store.close()
    return 0


#: The line of /metrics that says the service has loaded its strategies.
READY = "focustrack_estimator_strategies_loaded 1.0"


def spawn(
    store: str | Path,
    port: int,
    token: str | None = None,
    timeout_s: float = 60.0,
    options: Sequence[str] = (),
) -> Popen:
    """Start the service on 127.0.0.1:`port` as a child process; return once it answers and
    has loaded its strategies (its /metrics say so), as ready for a first slide as it gets.

    For the end-to-end tests and `focustrack bench api`, which need the server in
    a process of its own (to kill it, or to keep its CPU apart from the client's).
    `options`: more of the command's flags (`--max-live-slides`, `2`, ...).
    """
    env = dict(os.environ)
    if token:
        env[EstimatorSettings.variable("token")] = token
    import httpx  # for the tests and benchmarks that spawn a server, not for the server

    command = [sys.executable, "-m", "focustrack_estimator"]
    command += ["--port", str(port), "--store", str(store), *options]
    process = Popen(command, env=env, stdout=DEVNULL)
    deadline_s = time.monotonic() + timeout_s
    # One client for every probe: making one costs about 50 ms of CPU (its TLS context),
    # which a probe every 50 ms would take from the service starting beside it.
    with httpx.Client(timeout=1.0) as http:
        while time.monotonic() < deadline_s:
            if process.poll() is not None:
                raise RuntimeError(
                    f"estimator exited with {process.returncode} before it was ready"
                )
            try:
                metrics = http.get(f"http://127.0.0.1:{port}/metrics")
                if READY in metrics.text.splitlines():
                    return process
            except httpx.TransportError:
                pass
            time.sleep(0.05)
    process.kill()
    raise RuntimeError(f"estimator did not answer on port {port} within {timeout_s} s")


#: The `focustrack-estimator` console script (and `python -m focustrack_estimator`).
main = command_main("focustrack-estimator", "the estimator REST service", EstimatorSettings, run)
