"""`focustrack bench scale`: cost per tile, final map and restart as the slide grows.

For every strategy and grid size (square grids, `--sizes` columns) one child
process scans a generated standard surface (measurement noise 1.5 um) in
process, through the strategy's two calls, every tile of the full grid, and
reports:

- the time per tile (every acquisition of the tile: `next_acquisition` and
  `record`), mean and 99th percentile, in ms, both wall time and the thread's
  CPU time: on a shared machine a process waits for a core for milliseconds
  at a time, which sets the wall-time p99; the CPU time is what an idle core
  takes;
- the time of the final map (`focus_map()` once the scan is complete: for
  kf-2d the smoothed layers) in s, wall and CPU;
- the process's peak resident memory (the child's own, so cases do not mix),
  and its resident memory before the scan (imports and maps) for reference.

For the `--rest` strategies a second child fills a real store through the
service's own code (`Slides`, snapshots every `--snapshot-every`), all but the
last `--unsnapshotted` measurements, and stops as a kill -9 would: no shutdown
snapshot. The estimator service is then started on that store as a process
and the scan finished over HTTP (the first /next replays the events after the
snapshot), every map format fetched, the server killed with SIGKILL and
started again: `up` is process start to /healthz, `first answer` /healthz to
the slide's first /next (loading its snapshot), then every map format is
fetched and timed again. Each is reported as wall time and the server
process's CPU time (/proc). The store is filled with SQLite's fsync off
(`PRAGMA synchronous=OFF`): it measures restarts, not a disk.

Children run with one BLAS thread (`OPENBLAS_NUM_THREADS=1`), `--jobs` at a
time, the longest first; each reports its CPU time (imports and the servers
it started included), and the run their sum: divided by the jobs, it is the
run's wall time on idle cores.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from focustrack.arguments import output_file, positive_int, whole_number
from focustrack.bench.json_report import write_json
from focustrack_core.geometry import MAX_GRID_SIDE
from focustrack_core.rest import to_api, to_domain
from focustrack_core.rest.to_domain import default_settings
from focustrack_estimator import registry
from focustrack_estimator.replay import simulated_measurement

DEFAULT_SIZES = (20, 50, 100, 200)
DEFAULT_STRATEGIES = (
    "kf-2d",
    "kf-wiener0",
    "kf-wiener1",
    "kf-wiener2",
    "kf-gm1",
    "kf-gm2",
    "kf-wiener1-dir",
    "kf-mmae",
)
DEFAULT_REST = ("kf-2d", "kf-wiener0")
NOISE_UM = 1.5
SEED = 1000


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _surface(size: int) -> tuple[np.ndarray, Any]:
    """Measured heights (um) of a standard surface of size x size tiles, and the settings."""
    from focustrack_core.geometry import ScanGrid
    from focustrack_core.surfaces import SurfaceSpec, generate_surfaces

    truth_um = generate_surfaces(SurfaceSpec(rows=size, cols=size), 1, seed=SEED)[0]
    noise_um = np.random.default_rng(SEED).normal(0.0, NOISE_UM, truth_um.shape)
    return truth_um + noise_um, default_settings(ScanGrid(size, size))


def case_in_process(strategy_name: str, size: int) -> dict[str, Any]:
    """One in-process scan: per-tile times, final-map time, peak memory (run in a child)."""
    measured_um, settings = _surface(size)
    rss_before_mb = _peak_rss_mb()
    strategy = registry.create(strategy_name, settings)
    tile_s = np.zeros(settings.grid.shape)  # wall time
    tile_cpu_s = np.zeros(settings.grid.shape)  # this thread's CPU time
    while True:
        start_s, start_cpu_s = time.perf_counter(), time.thread_time()
        acquisition = strategy.next_acquisition()
        if acquisition is None:
            break
        measurement = simulated_measurement(
            acquisition, measured_um[acquisition.row, acquisition.col]
        )
        strategy.record(acquisition, measurement)
        tile_s[acquisition.row, acquisition.col] += time.perf_counter() - start_s
        tile_cpu_s[acquisition.row, acquisition.col] += time.thread_time() - start_cpu_s
    start_s, start_cpu_s = time.perf_counter(), time.thread_time()
    strategy.focus_map()
    map_s, map_cpu_s = time.perf_counter() - start_s, time.thread_time() - start_cpu_s
    return {
        "strategy": strategy_name,
        "cols": size,
        "tiles": size * size,
        "tile_mean_ms": float(np.mean(tile_s)) * 1e3,
        "tile_p99_ms": float(np.percentile(tile_s, 99)) * 1e3,
        "tile_cpu_mean_ms": float(np.mean(tile_cpu_s)) * 1e3,
        "tile_cpu_p99_ms": float(np.percentile(tile_cpu_s, 99)) * 1e3,
        "final_map_s": map_s,
        "final_map_cpu_s": map_cpu_s,
        "peak_rss_mb": _peak_rss_mb(),
        "rss_before_scan_mb": rss_before_mb,
    }


def fill_store(
    strategy_name: str, size: int, store_path: str, unsnapshotted: int, every: int
) -> str:
    """Scan into a store as the service does, and stop `unsnapshotted` measurements after a
    periodic snapshot (as a kill -9 would), near the end of the scan."""
    from focustrack_estimator.slide import Slide
    from focustrack_estimator.sqlite_store import SQLiteStore

    measured_um, settings = _surface(size)
    store = SQLiteStore(store_path)
    store._db.execute("PRAGMA synchronous=OFF")  # a benchmark's shortcut (module docstring)
    config = to_api.slide_create(strategy_name, settings)
    slide_id = "bench"
    store.create_slide(slide_id, config.model_dump(mode="json"))
    record = store.slide(slide_id)
    assert record is not None  # just created
    slide = Slide.load(record, store, snapshot_every=every)
    while (acquisition := slide.next()) is not None:
        n_logged = len(slide.history)  # every acquisition is at least one per tile
        if n_logged >= settings.grid.n_tiles - every and n_logged % every == unsnapshotted % every:
            break
        measured = measured_um[acquisition.row, acquisition.col]
        slide.measure(
            to_api.measurement_in(acquisition, simulated_measurement(acquisition, measured))
        )
    store.close()
    return slide_id


def case_rest(strategy_name: str, size: int, unsnapshotted: int, every: int) -> dict[str, Any]:
    """Restart of a served slide after kill -9: first answer and map formats (run in a child)."""
    import httpx

    from focustrack_client import EstimatorClient
    from focustrack_core.wire.session import free_port
    from focustrack_estimator.service import spawn

    # One client for every request: making one costs about 50 ms (its TLS context), which
    # each timed request would otherwise carry.
    with (
        tempfile.TemporaryDirectory() as directory,
        httpx.Client(timeout=120.0) as http,
    ):
        store_path = str(Path(directory) / "estimator.sqlite")
        slide_id = fill_store(strategy_name, size, store_path, unsnapshotted, every)
        measured_um, _ = _surface(size)
        port = free_port()
        url = f"http://127.0.0.1:{port}/v1/slides/{slide_id}"

        def start() -> tuple[subprocess.Popen, dict[str, float]]:
            """Start the server and ask for the slide's first /next: wall and server CPU times."""
            start_s = time.perf_counter()
            process = spawn(store_path, port, timeout_s=120.0)
            up_s, up_cpu_s = time.perf_counter(), _process_cpu_s(process.pid)
            response = http.get(f"{url}/next")
            response.raise_for_status()
            return process, {
                "up_s": up_s - start_s,
                "up_cpu_s": up_cpu_s,
                "first_answer_s": time.perf_counter() - up_s,
                "first_answer_cpu_s": _process_cpu_s(process.pid) - up_cpu_s,
            }

        def maps(pid: int) -> tuple[dict[str, float], dict[str, float]]:
            """Each format's time, wall and the server's CPU."""
            times, cpu_times = {}, {}
            for map_format in ("json", "csv", "npy", "png"):
                start_s, start_cpu_s = time.perf_counter(), _process_cpu_s(pid)
                http.get(f"{url}/map", params={"format": map_format}).raise_for_status()
                times[map_format] = time.perf_counter() - start_s
                cpu_times[map_format] = _process_cpu_s(pid) - start_cpu_s
            return times, cpu_times

        process, first = start()
        try:
            # The last measurement also makes the final map and its snapshot: allow it time.
            client = EstimatorClient(f"http://127.0.0.1:{port}", timeout_s=300.0)
            while (
                acquisition := to_domain.acquisition(client.next(slide_id))
            ) is not None:  # finish
                measured = measured_um[acquisition.row, acquisition.col]
                client.measure(
                    slide_id,
                    to_api.measurement_in(
                        acquisition, simulated_measurement(acquisition, measured)
                    ),
                )
            client.close()
            n_acquisitions = http.get(url).json()["n_acquisitions"]
            maps(process.pid)  # the complete scan's (its smoothed layers were made at its end)
            process.send_signal(signal.SIGKILL)
            process.wait()
            process, after_kill = start()
            slide = http.get(url).json()
            map_s, map_cpu_s = maps(process.pid)
            process.terminate()
            process.wait()
        finally:
            if process.poll() is None:
                process.kill()
    return {
        "strategy": strategy_name,
        "cols": size,
        "replayed_at_first_start": unsnapshotted % every,
        "first_answer_s": first["first_answer_s"],
        "first_answer_cpu_s": first["first_answer_cpu_s"],
        "up_after_kill_s": after_kill["up_s"],
        "up_after_kill_cpu_s": after_kill["up_cpu_s"],
        "first_answer_after_kill_s": after_kill["first_answer_s"],
        "first_answer_after_kill_cpu_s": after_kill["first_answer_cpu_s"],
        "lost_nothing": slide["n_acquisitions"] == n_acquisitions and slide["done"],
        "map_s": map_s,
        "map_cpu_s": map_cpu_s,
    }


def _process_cpu_s(pid: int) -> float:
    """A process's CPU time so far (user and system, all its threads), from /proc (Linux)."""
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rpartition(")")[2].split()  # after the command's name
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _child(arguments: list[str]) -> dict[str, Any]:
    """Run one case in a child; a failed case is reported (its error's last line), not fatal."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    command = [sys.executable, "-m", "focustrack.bench.scale", *arguments]
    # stderr to a file, not a pipe: a server the child started must not hold the pipe open.
    with tempfile.TemporaryFile("w+") as errors:
        result = subprocess.run(command, env=env, stdout=subprocess.PIPE, stderr=errors, text=True)
        errors.seek(0)
        error = errors.read().strip().splitlines()
    if result.returncode != 0:
        print(f"{' '.join(arguments)} failed:\n" + "\n".join(error[-20:]), file=sys.stderr)
        return {"strategy": arguments[1], "cols": int(arguments[2]), "error": error[-1:]}
    return json.loads(result.stdout.strip().splitlines()[-1])


#: The most cases run at once (each a process with its own estimator).
MAX_JOBS = 64


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sizes", type=whole_number(1, MAX_GRID_SIDE), nargs="+", default=list(DEFAULT_SIZES)
    )
    parser.add_argument(
        "--strategies",
        nargs="+",
        default=list(DEFAULT_STRATEGIES),
        choices=list(registry.STRATEGIES),
    )
    parser.add_argument(
        "--rest", nargs="*", default=list(DEFAULT_REST), help="strategies also served and restarted"
    )
    parser.add_argument("--snapshot-every", type=positive_int, default=200)
    parser.add_argument(
        "--unsnapshotted",
        type=whole_number(0),
        default=150,
        help="measurements after the last snapshot when the server is killed",
    )
    parser.add_argument(
        "--jobs",
        type=whole_number(1, MAX_JOBS),
        default=2,
        help=f"cases run at once, at most {MAX_JOBS}",
    )
    parser.add_argument("--json", type=output_file, metavar="OUT", help="write the figures as JSON")
    parser.add_argument(
        "--plot",
        type=output_file,
        metavar="PNG",
        help="time per tile against width (default: beside OUT)",
    )


def _table(in_process: list[dict[str, Any]], rest: list[dict[str, Any]]) -> str:
    lines = [
        "in process, one BLAS thread; wall time, and this thread's CPU time (what an idle core"
        " would take), every tile of the full grid:",
        f"{'strategy':<16}{'cols':>6}{'tile mean ms':>14}{'tile p99 ms':>13}{'CPU mean':>10}"
        f"{'CPU p99':>9}{'final map s':>13}{'CPU s':>7}{'peak RSS MB':>13}{'RSS before MB':>15}",
    ]
    for r in in_process:
        lines.append(
            f"{r['strategy']:<16}{r['cols']:>6}{r['tile_mean_ms']:>14.2f}{r['tile_p99_ms']:>13.2f}"
            f"{r['tile_cpu_mean_ms']:>10.2f}{r['tile_cpu_p99_ms']:>9.2f}"
            f"{r['final_map_s']:>13.3f}{r['final_map_cpu_s']:>7.2f}"
            f"{r['peak_rss_mb']:>13.0f}{r['rss_before_scan_mb']:>15.0f}"
        )
    if rest:
        lines += [
            "",
            "served: a completed scan, its server killed with SIGKILL and started again; up is"
            " process start to /healthz (imports), first answer /healthz to the slide's first"
            " /next; each figure wall time / the server's CPU time, in s:",
            f"{'strategy':<16}{'cols':>6}{'up':>13}{'first answer':>14}{'lost nothing':>14}"
            + "".join(f"{name:>13}" for name in ("map json", "csv", "npy", "png")),
        ]
        for r in rest:
            m, c = r["map_s"], r["map_cpu_s"]
            up = f"{r['up_after_kill_s']:.2f}/{r['up_after_kill_cpu_s']:.2f}"
            first = f"{r['first_answer_after_kill_s']:.2f}/{r['first_answer_after_kill_cpu_s']:.2f}"
            lines.append(
                f"{r['strategy']:<16}{r['cols']:>6}{up:>13}{first:>14}{r['lost_nothing']!s:>14}"
                + "".join(f"{f'{m[k]:.2f}/{c[k]:.2f}':>13}" for k in ("json", "csv", "npy", "png"))
            )
    return "\n".join(lines)


def _plot(in_process: list[dict[str, Any]], path: Path) -> None:
    """Mean and p99 time per tile, and the final map's time, against the width: CPU time
    (what an idle core takes) solid, wall time on this machine dotted."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(13, 4.2), layout="constrained")
    FigureCanvasAgg(figure)
    panels = figure.subplots(1, 3)
    keys = (
        ("tile_cpu_mean_ms", "tile_mean_ms"),
        ("tile_cpu_p99_ms", "tile_p99_ms"),
        ("final_map_cpu_s", "final_map_s"),
    )
    sizes = sorted({r["cols"] for r in in_process})
    for i, name in enumerate(dict.fromkeys(r["strategy"] for r in in_process)):
        rows = [r for r in in_process if r["strategy"] == name]
        cols = [r["cols"] for r in rows]
        for axes, (cpu, wall) in zip(panels, keys, strict=True):
            axes.plot(cols, [r[cpu] for r in rows], "o-", color=f"C{i}", label=name)
            axes.plot(cols, [r[wall] for r in rows], ":", color=f"C{i}", alpha=0.5)
    labels = ("mean time per tile (ms)", "p99 time per tile (ms)", "final map (s)")
    for axes, label, target in zip(panels, labels, (5.0, 10.0, 5.0), strict=True):
        axes.set(xlabel="columns (square grid)", ylabel=label, xscale="log", yscale="log")
        axes.set_xticks(sizes, [str(size) for size in sizes])
        axes.minorticks_off()
        axes.axhline(target, color="grey", linestyle="--", linewidth=0.8)
    panels[0].legend(fontsize="small", title="CPU solid, wall dotted", title_fontsize="small")
    figure.suptitle("kf-2d targets at 200 columns dashed")
    figure.savefig(path, dpi=100)


def _cost(arguments: list[str]) -> float:
    """A case's rough cost, to start the longest first (tiles, kf-2d and served ones more)."""
    tiles = int(arguments[2]) ** 2
    return (
        tiles * (4.0 if arguments[1] == "kf-2d" else 1.0) * (3.0 if arguments[0] == "rest" else 1.0)
    )


def run(args: argparse.Namespace) -> int:
    started_s = time.perf_counter()
    cases = [["in-process", name, str(size)] for size in args.sizes for name in args.strategies]
    rest_arguments = [str(args.unsnapshotted), str(args.snapshot_every)]
    cases += [
        ["rest", name, str(size), *rest_arguments] for size in args.sizes for name in args.rest
    ]
    print(
        f"{len(cases)} cases, {args.jobs} at a time, longest first; every tile of every grid",
        file=sys.stderr,
        flush=True,
    )

    def one(arguments: list[str]) -> dict[str, Any]:
        result = _child(arguments)
        print(
            f"[{time.perf_counter() - started_s:6.0f} s] {' '.join(arguments[:3])} done",
            file=sys.stderr,
            flush=True,
        )
        return {"kind": arguments[0], **result}

    longest_first = sorted(cases, key=_cost, reverse=True)
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        done = dict(zip(map(tuple, longest_first), pool.map(one, longest_first), strict=True))
    results = [done[tuple(arguments)] for arguments in cases]  # in the table's order
    failed = [r for r in results if "error" in r]
    in_process = [r for r in results if r["kind"] == "in-process" and "error" not in r]
    rest = [r for r in results if r["kind"] == "rest" and "error" not in r]
    for r in failed:
        print(f"FAILED: {r['kind']} {r['strategy']} {r['cols']}: {r['error']}")
    print(_table(in_process, rest))
    elapsed_s = time.perf_counter() - started_s
    cpu_s = sum(r.get("case_cpu_s", 0.0) for r in results)
    print(
        f"\n{len(cases)} cases in {elapsed_s:.0f} s, {args.jobs} at a time; {cpu_s:.0f} s of CPU "
        f"in all ({cpu_s / max(1, args.jobs):.0f} s on {args.jobs} idle cores); load average "
        + " ".join(f"{load:.1f}" for load in os.getloadavg())
    )
    if args.json:
        figures = {
            "in_process": in_process,
            "rest": rest,
            "failed": failed,
            "elapsed_s": elapsed_s,
            "cpu_s": cpu_s,
            "jobs": args.jobs,
            "load_average": os.getloadavg(),
        }
        write_json(args.json, figures)
    plot = args.plot or (args.json.with_suffix(".png") if args.json else None)
    if plot and in_process:
        _plot(in_process, plot)
        print(f"plot: {plot}")
    return 1 if failed else 0


def _main(argv: list[str]) -> None:
    """A child: one case, its figures as one JSON line on stdout."""
    kind, name, size = argv[0], argv[1], int(argv[2])
    if kind == "in-process":
        result = case_in_process(name, size)
    else:
        result = case_rest(name, size, int(argv[3]), int(argv[4]))
    # The case's CPU time, imports and the servers it started included: their sum over the
    # cases, divided by the jobs, is the run's wall time on idle cores.
    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    result["case_cpu_s"] = sum(u.ru_utime + u.ru_stime for u in usage)
    print(json.dumps(result))


if __name__ == "__main__":
    _main(sys.argv[1:])
