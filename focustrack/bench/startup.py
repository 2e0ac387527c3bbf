"""`focustrack bench startup`: how long each service takes from exec to its first answer.

Each service is started `--runs` times as a process of its own, as a container or the
demo starts it, and timed from exec until it answers:

- the estimator and the focus service: ``GET /healthz`` answers 200;
- the instrument: its info queryable answers over Zenoh (it has no HTTP);
- the scan command, which is no server: ``focustrack scan --help`` exits.

Beside them, in the same run, the floor of an HTTP service on this stack: a FastAPI
app with nothing but ``/healthz`` under uvicorn (with numpy and pydantic-settings
imported, as every service has them), timed the same way. What a service takes beyond
it is its own.

The Zenoh services connect to a router started once beforehand (what they would find
running). Target: every service answers within 1 s on an idle machine. Most of a
start is imports (``python -X importtime``): a service imports what it serves when it
serves it. The figures are medians and ranges over the runs, in seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import zenoh

from focustrack_core.health import instrument_answers
from focustrack_core.wire.session import free_port, loopback_endpoint, open_session

#: The target of every service, seconds from exec to the first answer.
TARGET_S = 1.0

#: How long one start may take before the run counts as failed, seconds.
TIMEOUT_S = 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=int, default=5, help="starts per service (5)")
    parser.add_argument("--json", type=Path, help="write the figures to this JSON file")


@dataclass(frozen=True)
class Service:
    """A service to start: its command (given free ports) and how to tell it answers."""

    name: str
    command: Callable[[int, str, Path], list[str]]  # (HTTP port, router endpoint, a folder)
    answers: Callable[[int, zenoh.Session], bool]  # (HTTP port, a session on the router)


def _http_ok(port: int, _: zenoh.Session) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=0.5).status_code == 200
    except httpx.TransportError:
        return False


def _instrument_ok(_: int, session: zenoh.Session) -> bool:
    return instrument_answers(session, "startup", timeout_s=0.2)


#: The floor: the smallest service on the same stack (its port is the first argument).
FLOOR_APP = """
import sys
import fastapi, numpy, pydantic_settings, uvicorn
app = fastapi.FastAPI()
app.get("/healthz")(lambda: {"status": "ok"})
uvicorn.run(app, port=int(sys.argv[1]), log_level="warning", ws="none")
"""

SERVICES = (
    Service(
        "floor (FastAPI)",
        lambda port, _, __: ["-c", FLOOR_APP, str(port)],
        _http_ok,
    ),
    Service(
        "estimator",
        lambda port, _, folder: [
            *("-m", "focustrack_estimator", "--port", str(port)),
            *("--store", str(folder / "estimator.sqlite")),
        ],
        _http_ok,
    ),
    Service(
        "focus",
        lambda port, router, _: [
            "-m",
            "focustrack_focus",
            "--port",
            str(port),
            "--connect",
            router,
        ],
        _http_ok,
    ),
    Service(
        "instrument",
        lambda _, router, __: [
            *("-m", "focustrack_instrument_sim", "--name", "startup", "--connect", router),
        ],
        _instrument_ok,
    ),
)


def time_start(service: Service, router: str, session: zenoh.Session) -> float:
    """Seconds from exec of `service` until it answers (it is stopped afterwards)."""
    port = free_port()
    with tempfile.TemporaryDirectory() as folder:
        command = [sys.executable, *service.command(port, router, Path(folder))]
        start_s = time.perf_counter()
        process = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=dict(os.environ)
        )
        try:
            while not service.answers(port, session):
                if process.poll() is not None:
                    raise RuntimeError(f"{service.name} exited with {process.returncode}")
                if time.perf_counter() - start_s > TIMEOUT_S:
                    raise RuntimeError(f"{service.name} did not answer within {TIMEOUT_S:g} s")
                time.sleep(0.01)
            return time.perf_counter() - start_s
        finally:
            process.terminate()
            process.wait(10)


def time_help(argv: list[str]) -> float:
    """Seconds `python -m focustrack <argv>` takes to run (e.g. print its help)."""
    start_s = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "focustrack", *argv], check=True, stdout=subprocess.DEVNULL
    )
    return time.perf_counter() - start_s


@contextmanager
def router() -> Iterator[str]:
    """A Zenoh router in a process of its own; yields its endpoint."""
    endpoint = loopback_endpoint()
    command = [sys.executable, "-m", "focustrack_core.wire.router", "--listen", endpoint]
    process = subprocess.Popen(command, stderr=subprocess.DEVNULL)
    try:
        yield endpoint
    finally:
        process.terminate()
        process.wait(10)


def summary(times_s: list[float]) -> dict[str, float]:
    return {
        "median_s": statistics.median(times_s),
        "min_s": min(times_s),
        "max_s": max(times_s),
    }


def run(args: argparse.Namespace) -> int:
    if args.runs < 1:
        print("focustrack bench startup: --runs must be at least 1", file=sys.stderr)
        return 2
    results: dict[str, dict[str, float]] = {}
    with router() as endpoint, open_session(connect=[endpoint]) as session:
        for service in SERVICES:
            times_s = []
            for index in range(args.runs):
                times_s.append(time_start(service, endpoint, session))
                print(
                    f"{service.name}: run {index + 1}/{args.runs} {times_s[-1]:.2f} s", flush=True
                )
            results[service.name] = summary(times_s)
    results["scan --help"] = summary([time_help(["scan", "--help"]) for _ in range(args.runs)])
    print(f"\nFrom exec to the first answer (s), {args.runs} runs each; target {TARGET_S:g} s:")
    print(f"{'service':<16}{'median':>9}{'min':>8}{'max':>8}  target")
    for name, figures in results.items():
        met = "met" if figures["median_s"] <= TARGET_S else "NOT met"
        print(
            f"{name:<16}{figures['median_s']:>9.2f}{figures['min_s']:>8.2f}"
            f"{figures['max_s']:>8.2f}  {met}"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"runs": args.runs, "target_s": TARGET_S, "services": results}
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
