"""`focustrack bench startup`: how long each service takes from exec to its first answer.

Each service is started `--runs` times as a process of its own, as a container or the
demo starts it, and timed from exec until it answers:

- the estimator and the focus service: ``GET /healthz`` answers 200;
- the instrument: its info queryable answers over Zenoh (it has no HTTP);
- the scan command, which is no server: ``focustrack scan --help`` exits.

Beside them, in the same run, the floor of an HTTP service on this stack: a FastAPI
app with nothing but ``/healthz`` under uvicorn (numpy imported, as every service has
it), timed the same way. What a service takes beyond it is its own.

``--compare PYTHON`` times the same services of another checkout (its virtualenv's
interpreter, e.g. one of the code before a change) in the same run, each run of one
interleaved with a run of the other, so that both see the same machine.

The Zenoh services connect to a router started once beforehand (what they would find
running). Target: every service answers within 1 s on an idle machine. Most of a
start is imports (``python -X importtime``): a service imports what it serves when it
serves it. The figures are medians and ranges over the runs, in seconds.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import zenoh

from focustrack.arguments import count_number, output_file
from focustrack.bench.json_report import write_json
from focustrack_core.health import instrument_answers, probe_http
from focustrack_core.wire.session import free_port, loopback_endpoint, open_session

#: The target of every service, seconds from exec to the first answer.
TARGET_S = 1.0

#: How long one start may take before the run counts as failed, seconds.
TIMEOUT_S = 60.0

#: The label of this checkout's interpreter in the results.
THIS = "this checkout"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=count_number, default=5, help="starts per service (5)")
    parser.add_argument(
        "--compare",
        type=Path,
        metavar="PYTHON",
        help="also time the services of another checkout: its virtualenv's python",
    )
    parser.add_argument("--json", type=output_file, help="write the figures to this JSON file")


@dataclass(frozen=True)
class Service:
    """A service to start: its arguments to python (given an HTTP port, the router's
    endpoint and a folder of its own) and how to tell it answers."""

    name: str
    arguments: Callable[[int, str, Path], list[str]]
    answers: Callable[[int, zenoh.Session], bool]  # (HTTP port, a session on the router)


def _http_ok(port: int, _: zenoh.Session) -> bool:
    # urllib, not an httpx client: making one costs about 50 ms of CPU (its TLS context),
    # which every probe would add to the start it times.
    try:
        probe_http(f"http://127.0.0.1:{port}/healthz", timeout_s=0.5)
    except OSError:
        return False
    return True


def _instrument_ok(_: int, session: zenoh.Session) -> bool:
    return instrument_answers(session, "startup", timeout_s=0.2)


def _exits(_: int, __: zenoh.Session) -> bool:
    return True  # a command that is done when its process is (`time_start` waits for it)


#: The floor: the smallest service on the same stack (its port is the first argument).
FLOOR_APP = """
import sys
import fastapi, numpy, uvicorn
app = fastapi.FastAPI()
app.get("/healthz")(lambda: {"status": "ok"})
uvicorn.run(app, port=int(sys.argv[1]), log_level="warning", ws="none")
"""

SERVICES = (
    Service("floor (FastAPI)", lambda port, _, __: ["-c", FLOOR_APP, str(port)], _http_ok),
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
            *("-m", "focustrack_focus", "--port", str(port), "--connect", router),
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
    Service("scan --help", lambda _, __, ___: ["-m", "focustrack", "scan", "--help"], _exits),
)


def time_start(python: Path, service: Service, router: str, session: zenoh.Session) -> float:
    """Seconds from exec of `service` with `python` until it answers (then it is stopped);
    for a command that is no server, until it has exited with status 0."""
    port = free_port()
    with tempfile.TemporaryDirectory() as folder:
        command = [str(python), *service.arguments(port, router, Path(folder))]
        start_s = time.perf_counter()
        # Run from a folder of its own: `-m` puts the working directory first on the path,
        # and a checkout's root holds the `focustrack` package of that checkout.
        process = subprocess.Popen(
            command, cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        try:
            if service.answers is _exits:
                if process.wait(TIMEOUT_S) != 0:
                    raise RuntimeError(f"{service.name} exited with {process.returncode}")
                return time.perf_counter() - start_s
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
    return {"median_s": statistics.median(times_s), "min_s": min(times_s), "max_s": max(times_s)}


def measure(pythons: dict[str, Path], runs: int) -> dict[str, dict[str, dict[str, float]]]:
    """{label: {service: summary}}: every service started `runs` times with each python,
    the pythons' runs interleaved."""
    times_s: dict[str, dict[str, list[float]]] = {
        label: {service.name: [] for service in SERVICES} for label in pythons
    }
    with router() as endpoint, open_session(connect=[endpoint]) as session:
        for service in SERVICES:
            for index in range(runs):
                for label, python in pythons.items():
                    seconds = time_start(python, service, endpoint, session)
                    times_s[label][service.name].append(seconds)
                    print(f"{label}: {service.name} run {index + 1}/{runs} {seconds:.2f} s")
    return {
        label: {name: summary(values) for name, values in by_service.items()}
        for label, by_service in times_s.items()
    }


def run(args: argparse.Namespace) -> int:
    pythons = {THIS: Path(sys.executable)}
    if args.compare is not None:
        if not args.compare.is_file():
            print(f"focustrack bench startup: no python at {args.compare}", file=sys.stderr)
            return 2
        pythons[str(args.compare)] = args.compare
    results = measure(pythons, args.runs)
    for label, by_service in results.items():
        print(f"\n{label}: from exec to the first answer (s), {args.runs} runs each; "
              f"target {TARGET_S:g} s")  # fmt: skip
        print(f"{'service':<16}{'median':>9}{'min':>8}{'max':>8}  target")
        for name, figures in by_service.items():
            met = "met" if figures["median_s"] <= TARGET_S else "NOT met"
            print(
                f"{name:<16}{figures['median_s']:>9.2f}{figures['min_s']:>8.2f}"
                f"{figures['max_s']:>8.2f}  {met}"
            )
    if args.json:
        payload = {
            "runs": args.runs,
            "target_s": TARGET_S,
            "services": results[THIS],
            "compared": {label: figures for label, figures in results.items() if label != THIS},
        }
        write_json(args.json, payload)
        print(f"wrote {args.json}")
    return 0
