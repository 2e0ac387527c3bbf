"""End to end on loopback: a Zenoh router (this process), the instrument, focus and estimator
services and `focustrack scan`, each a real process; services killed and restarted mid-scan."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zarr

from focustrack.demo import LIVE_VIEW_PNG, SECOND_PASS
from focustrack.local_stack import LocalStack
from focustrack_core import health
from focustrack_core.fusion import fuse_planes
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_policy, default_settings
from focustrack_core.surfaces import add_measurement_noise
from focustrack_core.wire import session
from focustrack_core.wire.session import free_port
from focustrack_estimator import registry
from focustrack_estimator.replay import replay, score
from focustrack_scheduler import outputs
from focustrack_scheduler.clients import InstrumentClient
from focustrack_scheduler.mosaic_store import to_uint8
from focustrack_scheduler.settings import BEST_KALMAN

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

ROWS = COLS = 6
SIZE = 256
STRATEGY = BEST_KALMAN
NOISE_UM = 0.1  # what the scan assumes by default (the focus service does better)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    instrument_args = [
        "--seed", "5", "--slides", "1", "--rows", str(ROWS), "--cols", str(COLS),
        "--width", str(SIZE), "--height", str(SIZE),
    ]  # fmt: skip
    with LocalStack(tmp_path_factory.mktemp("stack"), instrument_args) as running:
        yield running


def scan_command(stack: LocalStack, out_dir: Path, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "focustrack", "scan", "--no-progress",
        "--estimator", stack.estimator_url, "--connect", stack.endpoint,
        "--instrument", "sim", "--slide", "slide-0", "--strategy", STRATEGY,
        "--out", str(out_dir), *extra,
    ]  # fmt: skip


def start_scan(stack: LocalStack, out_dir: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        scan_command(stack, out_dir, *extra),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=os.environ | {"PYTHONUNBUFFERED": "1"},
    )


def acquisitions_logged(out_dir: Path) -> int:
    path = out_dir / outputs.LOG_FILE
    if not path.exists():
        return 0
    return path.read_text().count('"event": "acquired"')


def wait_for_acquisitions(process: subprocess.Popen, out_dir: Path, n: int) -> None:
    deadline_s = time.monotonic() + 120
    while acquisitions_logged(out_dir) < n:
        assert process.poll() is None, f"scan ended early: {process.communicate()}"
        assert time.monotonic() < deadline_s, "the scan made no progress"
        time.sleep(0.02)


def finish(process: subprocess.Popen, timeout_s: float = 180) -> tuple[str, str]:
    stdout, stderr = process.communicate(timeout=timeout_s)
    assert process.returncode == 0, stderr
    return stdout, stderr


def report_of(out_dir: Path) -> dict:
    return json.loads((out_dir / outputs.REPORT).read_text())


def assert_complete(http: httpx.Client, stack: LocalStack, out_dir: Path) -> dict:
    """The scan imaged every tile once, the estimator agrees, and the outputs are all there."""
    report = report_of(out_dir)
    assert report["tiles_imaged"] == ROWS * COLS
    slide_id = report["estimator_slide_id"]
    slide = http.get(f"{stack.estimator_url}/v1/slides/{slide_id}").json()
    assert slide["done"] is True
    logged = [json.loads(line) for line in (out_dir / outputs.LOG_FILE).read_text().splitlines()]
    sequences = {entry["sequence"] for entry in logged if entry["event"] == "acquired"}
    assert sequences == set(range(slide["n_acquisitions"]))  # every one asked for was made
    mosaic = np.asarray(zarr.open_group(out_dir / outputs.MOSAIC_ZARR, mode="r")["s0"])
    assert mosaic.shape == (3, ROWS * SIZE, COLS * SIZE)  # the default OME-Zarr, (c, y, x)
    mosaic = mosaic.transpose(1, 2, 0)
    tiles = mosaic.reshape(ROWS, SIZE, COLS, SIZE, 3)
    assert (tiles.std(axis=(1, 3, 4)) > 0).all()  # every tile holds an image
    assert not (out_dir / outputs.PARTIAL_MOSAIC).exists()
    table = np.load(out_dir / outputs.FOCUS_MAP_NPY)
    assert np.isfinite(table["posterior_sigma_um"]).all()
    for name in (outputs.FOCUS_MAP_CSV, outputs.PLOTS, outputs.MOSAIC_PREVIEW):
        assert (out_dir / name).stat().st_size > 0
    return report


def benchmark_prediction(stack: LocalStack, dof_um: float):
    """What `focustrack bench accuracy` predicts for this slide's truth at the scan's noise."""
    assert stack.session is not None
    truth_um = InstrumentClient(stack.session, "sim").truth_um("slide-0")
    measured_um = add_measurement_noise(truth_um[None], NOISE_UM, seed=0)[0]
    settings = default_settings(ScanGrid(ROWS, COLS), dof_um=dof_um, noise_sigma_um=NOISE_UM)
    return score([replay(registry.create(STRATEGY, settings), truth_um, measured_um)], dof_um)


def test_a_scan_completes_as_the_benchmark_predicts_and_resumes_after_a_kill(
    http: httpx.Client, stack: LocalStack, tmp_path: Path
) -> None:
    first = start_scan(stack, tmp_path)
    wait_for_acquisitions(first, tmp_path, 6)
    first.send_signal(signal.SIGKILL)
    first.wait()
    slide_id = json.loads((tmp_path / outputs.STATE_FILE).read_text())["slide_id"]
    assert not (tmp_path / outputs.REPORT).exists()

    stdout, _ = finish(start_scan(stack, tmp_path))
    assert f"{STRATEGY}: {ROWS * COLS} tiles" in stdout
    report = assert_complete(http, stack, tmp_path)
    assert report["estimator_slide_id"] == slide_id  # resumed, not started over
    assert len(http.get(f"{stack.estimator_url}/v1/slides").json()) >= 1

    predicted = benchmark_prediction(stack, report["dof_um"])
    # The benchmark's maps have no empty fields; the simulated slide has some (5%, and on
    # small frames sparse fields look empty too), where the focus curve is flat and the
    # estimator asks for the widest stack. Without those, the scan costs what the benchmark
    # predicts (give or take the stack in flight at the kill, taken twice, and edge flags,
    # which a real focus curve raises also when the peak is within half a step of an end).
    acquired = [
        entry
        for entry in map(json.loads, (tmp_path / outputs.LOG_FILE).read_text().splitlines())
        if entry["event"] == "acquired"
    ]
    max_frames = default_policy().max_frames
    flat = [e for e in acquired if e["purpose"] == "retry" and e["n_frames"] == max_frames]
    per_tile = (report["images_acquired"] - sum(e["n_frames"] for e in flat)) / (ROWS * COLS)
    assert 0.8 * predicted.images_per_tile <= per_tile <= 1.25 * predicted.images_per_tile + 0.5
    assert len({(e["row"], e["col"]) for e in flat}) <= 0.15 * ROWS * COLS
    assert report["in_focus_fraction"] >= predicted.in_focus_fraction - 0.1
    # the estimator's own expectation of it, from each tile's predicted risk
    assert report["predicted_in_focus_fraction"] == pytest.approx(
        report["in_focus_fraction"], abs=0.15
    )
    assert report["mae_um"] < 0.5 and report["scan_time_s"] > 0
    wall = report["wall_time_s"]
    assert wall["total_s"] > 0 and wall["rendering_s"] > 0 and wall["estimation_s"] > 0

    # Run again, finished: the same scan, its wall time that of every run (it was the
    # last run's alone, 0.1 s of nothing to do).
    finish(start_scan(stack, tmp_path))
    again = json.loads((tmp_path / outputs.REPORT).read_text())
    assert again["images_acquired"] == report["images_acquired"]
    assert again["wall_time_s"]["total_s"] > wall["total_s"]
    assert again["wall_time_s"]["rendering_s"] == pytest.approx(wall["rendering_s"])


@pytest.mark.parametrize("service", ["estimator", "focus"])
def test_a_service_killed_and_restarted_mid_scan_ends_in_a_complete_correct_scan(
    http: httpx.Client, stack: LocalStack, tmp_path: Path, service: str
) -> None:
    scan = start_scan(stack, tmp_path, "--focus-timeout-s", "4", "--focus-attempts", "6")
    wait_for_acquisitions(scan, tmp_path, 5)
    stack.services[service].kill()
    time.sleep(1.0)
    assert scan.poll() is None  # the scan waits for the service instead of failing
    stack.restart(service)
    _, stderr = finish(scan)
    report = assert_complete(http, stack, tmp_path)
    assert report["in_focus_fraction"] >= 0.85 and report["mae_um"] < 0.5
    if service == "focus":
        assert "acquiring it again" in stderr  # the lost stack was taken again


def test_a_missing_instrument_or_estimator_is_reported_not_waited_for(
    stack: LocalStack, tmp_path: Path
) -> None:
    started_s = time.monotonic()
    command = scan_command(stack, tmp_path / "a", "--instrument-outage-s", "2")
    command[command.index("--instrument") + 1] = "nosuch"
    missing = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert missing.returncode == 1
    assert "focustrack/v1/instrument/nosuch/info" in missing.stderr
    assert "Traceback" not in missing.stderr

    gone = f"http://127.0.0.1:{free_port()}"
    command = scan_command(stack, tmp_path / "b", "--estimator-outage-s", "2")
    command[command.index("--estimator") + 1] = gone
    unreachable = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert unreachable.returncode == 1
    assert f"estimator at {gone}" in unreachable.stderr
    assert time.monotonic() - started_s < 50

    # The container health probe (compose.yaml) tells the two cases apart as well.
    probe = ["--connect", stack.endpoint, "--timeout-s", "2"]
    assert health.main([*probe, "--instrument", "sim"]) == 0
    assert health.main([*probe, "--instrument", "nosuch"]) == 1
    assert health.main(["--http", f"{stack.estimator_url}/healthz"]) == 0
    assert health.main(["--http", f"{gone}/healthz", "--timeout-s", "2"]) == 1


def test_demo_compares_strategies_and_writes_json(tmp_path: Path) -> None:
    out_json = tmp_path / "demo.json"
    command = [
        sys.executable, "-m", "focustrack", "demo", "--rows", "3", "--cols", "3",
        "--size", "64", "--strategies", BEST_KALMAN, "af-every-tile", "--no-progress",
        "--no-screenshot", "--out", str(tmp_path / "demo"), "--json", str(out_json),
    ]  # fmt: skip
    demo = subprocess.run(command, capture_output=True, text=True, timeout=180)
    assert demo.returncode == 0, demo.stderr
    assert "images/tile" in demo.stdout and "transport" in demo.stdout
    # one host: the frames take shared memory where /dev/shm has room for the pool
    room = session.shared_memory_room_mb() >= session.SHARED_MEMORY_MB
    assert ("frames over shared memory" if room else "frames over TCP") in demo.stdout
    strategies = json.loads(out_json.read_text())["strategies"]
    # the second pass (kf-rescan with the first scan's map, after the focus moved) comes last
    assert list(strategies) == [BEST_KALMAN, "af-every-tile", SECOND_PASS]
    for figures in strategies.values():
        assert set(figures) >= {"images_per_tile", "scan_time_s", "in_focus_fraction", "mae_um"}
    assert strategies["af-every-tile"]["images_per_tile"] >= 41
    assert not (tmp_path / "demo" / LIVE_VIEW_PNG).exists()  # --no-screenshot: no browser
    assert (
        strategies[SECOND_PASS]["images_per_tile"]
        < strategies[BEST_KALMAN]["images_per_tile"]
        < strategies["af-every-tile"]["images_per_tile"]
    )
    # the services were stopped: no process still runs on the demo's estimator store
    store = str(tmp_path / "demo" / "estimator.sqlite")
    assert subprocess.run(["pgrep", "-f", store], capture_output=True).returncode == 1


def test_tiles_too_unsure_for_one_frame_keep_several_and_the_mosaic_fuses_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A focus measure whose peak strays 1.5 um (said in its sigma) against a depth of field
    under 1 um: kf-2d-lean keeps several frames of its unsure tiles, the scheduler writes
    them beside the mosaic, fuses them into the tile's image and judges focus on any."""
    monkeypatch.setenv("FOCUSTRACK_FOCUS_SYSTEMATIC_SIGMA_UM", "1.5")  # the focus service's
    instrument_args = [
        "--seed", "5", "--slides", "1", "--rows", "3", "--cols", "3",
        "--width", "128", "--height", "128",
    ]  # fmt: skip
    out_dir = tmp_path / "scan"
    with LocalStack(tmp_path / "stack", instrument_args) as noisy:
        command = scan_command(noisy, out_dir, "--noise-sigma-um", "1.5")
        command[command.index(STRATEGY)] = "kf-2d-lean"
        scan = subprocess.run(command, capture_output=True, text=True, timeout=180)
    assert scan.returncode == 0, scan.stderr
    report = report_of(out_dir)
    assert report["frames_kept_per_tile"] > 1.0
    logged = [json.loads(line) for line in (out_dir / outputs.LOG_FILE).read_text().splitlines()]
    planes = [entry for entry in logged if entry["event"] == "planes"]
    assert planes
    mosaic = np.asarray(zarr.open_group(out_dir / outputs.MOSAIC_ZARR, mode="r")["s0"])
    mosaic = mosaic.transpose(1, 2, 0)  # (y, x, c)
    for entry in planes:
        frames = np.load(out_dir / entry["file"])
        assert frames.shape[0] == len(entry["z_um"]) >= 2
        row, col = entry["row"], entry["col"]
        tile = mosaic[row * 128 : (row + 1) * 128, col * 128 : (col + 1) * 128]
        np.testing.assert_array_equal(tile, to_uint8(fuse_planes(frames), 12))
