"""`focustrack bench api`: latency and throughput of the estimator's REST API over loopback.

The service runs in a process of its own (`focustrack serve estimator`, uvicorn)
on a fresh SQLite store (or the PostgreSQL database of `--store`); this process
plays the scanners, each driving one slide through the `/next` + `/measurements`
pair with measurements simulated from a generated focus map
(`focustrack_estimator.replay.simulated_measurement`).

Cases:
- `1-slide`: one scanner, back to back (no acquisition time): the latency floor;
- `N-slides`: N scanners at once, each taking the simulated acquisition time
  of every stack (`TimingModel`: stage move + frames, as the accuracy benchmark
  costs it; `--time-scale` shrinks it) between `/next` and `/measurements`,
  as real instruments would. This is the service's working load;
- `N-slides-saturated`: N scanners back to back: the most pairs per second the
  service sustains (latency then is N / throughput, by Little's law).

A pair's latency is the time of its two requests (not the acquisition between
them). The share of time in the filter is the server's own account
(`/metrics`: time in strategy calls over time in the two routes).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx
import numpy as np

from focustrack.arguments import (
    count_number,
    finite_number,
    output_file,
    positive_float,
    seed_number,
    whole_number,
)
from focustrack.bench.json_report import write_json
from focustrack_client import models as api
from focustrack_core.geometry import MAX_GRID_SIDE, ScanGrid, Tile
from focustrack_core.rest import to_api, to_domain
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_core.timing import TimingModel
from focustrack_core.wire.session import free_port
from focustrack_estimator import registry
from focustrack_estimator.event_store import StoreError, store_address
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.service import spawn

PAIR_ROUTES = ("/v1/slides/{slide_id}/next", "/v1/slides/{slide_id}/measurements")


@dataclass(frozen=True)
class CaseResult:
    """One case: pair latency percentiles (ms), throughput, and the filter's share of time."""

    case: str
    slides: int
    pairs: int
    p50_ms: float
    p99_ms: float
    max_ms: float
    requests_per_s: float
    filter_share: float  # of the server's time in /next and /measurements


def _scrape(text: str) -> dict[str, float]:
    """Sums of the filter time and of the pair routes' request time, from /metrics text."""
    sums = {"filter": 0.0, "routes": 0.0}
    for line in text.splitlines():
        if line.startswith("focustrack_estimator_filter_duration_seconds_sum"):
            sums["filter"] += float(line.rsplit(" ", 1)[1])
        match = re.match(
            r'focustrack_estimator_request_duration_seconds_sum\{route="(.*)"\} (.*)', line
        )
        if match and match[1] in PAIR_ROUTES:
            sums["routes"] += float(match[2])
    return sums


class Connection:
    """A minimal HTTP/1.1 keep-alive client on one loopback connection, JSON in and out.

    Why not httpx: at 100 connections its AsyncClient spent about 6 ms of CPU per
    request pair on these 2 cores, more than the server, so the benchmark measured
    the client. This one costs tens of microseconds. It reads the Content-Length
    framed responses the service sends, nothing more.
    """

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def request(self, method: str, path: str, body: object = None) -> tuple[int, object]:
        if self._reader is None or self._writer is None:
            self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        payload = b"" if body is None else json.dumps(body).encode()
        head = (
            f"{method} {path} HTTP/1.1\r\nHost: {self.host}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(payload)}\r\n\r\n"
        )
        self._writer.write(head.encode() + payload)
        header = await self._reader.readuntil(b"\r\n\r\n")
        lines = header.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ", 2)[1])
        fields = dict(line.split(":", 1) for line in lines[1:] if ":" in line)
        length = int({k.lower(): v for k, v in fields.items()}["content-length"])
        return status, json.loads(await self._reader.readexactly(length))

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            await self._writer.wait_closed()


def _ok(reply: tuple[int, object]) -> dict:
    status, body = reply
    if status != 200 or not isinstance(body, dict):
        raise RuntimeError(f"estimator answered {status}: {body}")
    return body


class Scanner:
    """One simulated instrument scanning one slide through the API, on its own connection."""

    def __init__(
        self,
        http: Connection,
        slide_id: str,
        grid: ScanGrid,
        measured_um: np.ndarray,
        acquisition_s: float | None,
    ) -> None:
        self.http, self.slide_id, self.grid = http, slide_id, grid
        self.measured_um = measured_um
        self.acquisition_s = acquisition_s  # None: back to back; else TimingModel time x this
        self.latencies_s: list[float] = []
        self._timing = TimingModel()
        self._here: Tile | None = None

    async def run(self, start_delay_s: float, until_s: float) -> None:
        url = f"/v1/slides/{self.slide_id}"
        await asyncio.sleep(start_delay_s)
        try:
            while time.perf_counter() < until_s:
                start_s = time.perf_counter()
                reply = _ok(await self.http.request("GET", f"{url}/next"))
                elapsed_s = time.perf_counter() - start_s
                acquisition = to_domain.acquisition(api.Next.model_validate(reply))
                if acquisition is None:
                    return
                if self.acquisition_s is not None:
                    await asyncio.sleep(self.acquisition_s * self._simulated_s(acquisition))
                measured = self.measured_um[acquisition.row, acquisition.col]
                measurement = simulated_measurement(acquisition, measured)
                body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
                start_s = time.perf_counter()
                _ok(await self.http.request("POST", f"{url}/measurements", body))
                self.latencies_s.append(elapsed_s + time.perf_counter() - start_s)
        finally:
            await self.http.close()

    def _simulated_s(self, acquisition) -> float:
        tile = Tile(acquisition.row, acquisition.col)
        move_s = (
            0.0
            if self._here is None
            else self._timing.move_s(self.grid.distance_um(self._here, tile))
        )
        self._here = tile
        return move_s + self._timing.stack_s(acquisition.z.n_frames)


async def run_case(
    base_url: str,
    case: str,
    n_slides: int,
    args: argparse.Namespace,
    acquisition_s: float | None,
) -> CaseResult:
    grid = ScanGrid(args.size, args.size)
    settings = default_settings(grid, noise_sigma_um=args.noise_um)
    truths = generate_surfaces(SurfaceSpec(rows=args.size, cols=args.size), n_slides, args.seed)
    rng = np.random.default_rng(args.seed)
    url = httpx.URL(base_url)
    async with httpx.AsyncClient(base_url=base_url, timeout=30.0) as http:
        scanners = []
        for truth in truths:
            response = await http.post(
                "/v1/slides",
                json=to_api.slide_create(args.strategy, settings).model_dump(mode="json"),
            )
            response.raise_for_status()
            measured = truth + rng.normal(0.0, args.noise_um, truth.shape)
            connection = Connection(url.host, url.port or 80)
            slide_id = response.json()["id"]
            scanners.append(Scanner(connection, slide_id, grid, measured, acquisition_s))
        before = _scrape((await http.get("/metrics")).text)
        start_s = time.perf_counter()
        until_s = start_s + args.duration_s
        # Instruments are not synchronised: paced scanners start at random moments within
        # the first second (else all 100 ask at once, tile after tile, in lock step).
        delays_s = rng.uniform(0.0, 1.0, n_slides) * (acquisition_s or 0.0)
        await asyncio.gather(*(s.run(d, until_s) for s, d in zip(scanners, delays_s, strict=True)))
        wall_s = time.perf_counter() - start_s
        after = _scrape((await http.get("/metrics")).text)
    latencies_ms = 1e3 * np.concatenate([s.latencies_s for s in scanners])
    routes_s = after["routes"] - before["routes"]
    return CaseResult(
        case=case,
        slides=n_slides,
        pairs=latencies_ms.size,
        p50_ms=float(np.percentile(latencies_ms, 50)),
        p99_ms=float(np.percentile(latencies_ms, 99)),
        max_ms=float(latencies_ms.max()),
        requests_per_s=2 * latencies_ms.size / wall_s,
        filter_share=(after["filter"] - before["filter"]) / routes_s if routes_s else 0.0,
    )


def estimator_store(text: str) -> str:
    """argparse type: a store the estimator can open (`store_address`), checked before it
    is started."""
    try:
        store_address(text)
    except StoreError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--slides", type=count_number, default=100, help="concurrent slides (default 100)"
    )
    parser.add_argument(
        "--size", type=whole_number(1, MAX_GRID_SIDE), default=20, help="grid side in tiles (20)"
    )
    parser.add_argument(
        "--strategy",
        default="kf-wiener0",
        choices=list(registry.STRATEGIES),
        help="strategy of every slide",
    )
    parser.add_argument(
        "--noise-um",
        type=finite_number(api.MIN_SIGMA_UM, api.MAX_ABS_UM),  # what the API takes
        default=1.5,
        help="measurement noise std, um",
    )
    parser.add_argument("--seed", type=seed_number, default=2000, help="seed of the focus maps")
    parser.add_argument(
        "--duration-s",
        type=positive_float,
        default=15.0,
        help="how long each case runs (default 15 s)",
    )
    parser.add_argument(
        "--time-scale",
        type=positive_float,
        default=1.0,
        help="acquisition time of the paced case, as a multiple of the TimingModel's (default 1)",
    )
    parser.add_argument(
        "--store",
        type=estimator_store,
        help="the estimator's store: a PostgreSQL database's URL (postgresql://...; its "
        "tables must not hold other slides) or an SQLite file (default: a new one)",
    )
    parser.add_argument("--json", type=output_file, help="write the results here")


def run(args: argparse.Namespace) -> int:
    port = free_port()
    base_url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as directory:
        try:
            server = spawn(args.store or Path(directory) / "bench.sqlite", port)
        except RuntimeError as error:  # the estimator said why on stderr
            print(f"focustrack bench api: error: {error}", file=sys.stderr)
            return 1
        try:
            cases = [
                ("1-slide", 1, None),
                (f"{args.slides}-slides", args.slides, args.time_scale),
                (f"{args.slides}-slides-saturated", args.slides, None),
            ]
            results = []
            for name, n_slides, acquisition_s in cases:
                print(f"{name}: {args.duration_s:.0f} s ...", flush=True)
                try:
                    result = asyncio.run(run_case(base_url, name, n_slides, args, acquisition_s))
                except httpx.HTTPStatusError as error:  # a store down, say: its words
                    answer = error.response
                    print(
                        f"focustrack bench api: error: the estimator answered "
                        f"{answer.status_code} to {error.request.url.path}: {answer.text}",
                        file=sys.stderr,
                    )
                    return 1
                print(
                    f"  {result.pairs} pairs, p50 {result.p50_ms:.2f} ms,"
                    f" p99 {result.p99_ms:.2f} ms,"
                    f" max {result.max_ms:.1f} ms, {result.requests_per_s:.0f} requests/s, "
                    f"filter {100 * result.filter_share:.1f}% of server time",
                    flush=True,
                )
                results.append(result)
        finally:
            server.terminate()
            server.wait(timeout=10)
    if args.json:
        payload = {r.case: {k: v for k, v in asdict(r).items() if k != "case"} for r in results}
        write_json(args.json, payload)
        print(f"wrote {args.json}")
    return 0
