"""What a scan tells an operator: its metrics follow its record, its retries and steps; the
live view serves them (real uvicorn on loopback). The tiles' traces across the services are
checked end to end (tests/test_traces_e2e.py)."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np

from focustrack_core.domain import Acquisition, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_core.v1 import common_pb2
from focustrack_core.wire import rpc
from focustrack_scheduler.live_view import LiveServer
from focustrack_scheduler.plan import Acquire, AskNext, KeepTile, PostMeasurement
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy, instrument_retryable
from focustrack_scheduler.telemetry import ScanMetrics, TileSpans

GRID = ScanGrid(2, 2)
IMAGE = np.full((8, 8, 3), 100, np.uint8)


def value(metrics: ScanMetrics, name: str, **labels: str) -> float:
    sample = metrics.registry.get_sample_value(name, labels)
    assert sample is not None, name
    return sample


def acquisition(index: int, row: int, col: int) -> Acquisition:
    return Acquisition(index, row, col, ZRange(-1.0, 0.5, 5), Purpose.SCAN, True)


def test_the_metrics_follow_the_scans_record_and_count_a_tile_once(tmp_path: Path) -> None:
    record = ScanRecord(tmp_path)
    record.keep(GRID, 1, 1, 0.0, IMAGE, 8)  # before the metrics: a resumed scan's tile
    metrics = ScanMetrics()
    metrics.follow(record.tally.kept)
    record.listeners.add(metrics.take)
    first = acquisition(0, 0, 0)
    record.acquired(first, 5, 1.0)
    record.measurement(first, Measurement(0.1, 0.2), Outcome(0, 0, True, 0.1, 0.2), None)
    record.keep(GRID, 0, 0, 0.0, IMAGE, 8)
    record.keep(GRID, 0, 0, 0.5, IMAGE, 8)  # its image again, nearer the posterior
    record.keep(GRID, 1, 1, 0.0, IMAGE, 8)
    assert value(metrics, "focustrack_scan_acquisitions_total") == 1
    assert value(metrics, "focustrack_scan_frames_total") == 5
    assert value(metrics, "focustrack_scan_measurements_total") == 1
    assert value(metrics, "focustrack_scan_tiles_done_total") == 1
    assert value(metrics, "focustrack_scan_faults_total", kind="focus_timeout") == 0  # listed
    record.close()


def test_retries_are_counted_as_the_policy_pauses() -> None:
    metrics = ScanMetrics()
    failures = [rpc.RemoteError(common_pb2.Error(code=common_pb2.ERROR_CODE_BUSY))] * 2
    retried = metrics.retries.labels("instrument").inc

    def call() -> str:
        if failures:
            raise failures.pop()
        return "acquired"

    policy = RetryPolicy(backoff_initial_s=0.001, backoff_max_s=0.002)
    assert policy.retrying(60, instrument_retryable, "test", retried)(call) == "acquired"
    assert value(metrics, "focustrack_scan_retries_total", service="instrument") == 2
    assert value(metrics, "focustrack_scan_retries_total", service="estimator") == 0


def test_each_step_is_timed_and_a_tile_lasts_until_another_begins() -> None:
    metrics = ScanMetrics()
    tiles = TileSpans(metrics)
    first, second = acquisition(0, 0, 0), acquisition(1, 0, 1)
    steps = [
        AskNext("slide-id"),  # before any tile
        Acquire("slide-0", first),
        PostMeasurement("slide-id", first, Measurement(0.1)),
        AskNext("slide-id"),  # in the tile before it
        Acquire("slide-0", first, attempt=2),
        KeepTile(0, 0, 0, 2, 0.0),
        Acquire("slide-0", second),
    ]
    for step in steps:
        with tiles.step(step, "slide-0"):
            pass
    tiles_timed = "focustrack_scan_tile_duration_seconds_count"
    assert value(metrics, tiles_timed) == 1  # the first tile, once the second began
    tiles.close()
    assert value(metrics, tiles_timed) == 2
    timed = "focustrack_scan_step_duration_seconds_count"
    assert value(metrics, timed, step="Acquire") == 3
    assert value(metrics, timed, step="AskNext") == 2


def test_the_live_view_serves_the_scans_metrics(http: httpx.Client) -> None:
    metrics = ScanMetrics()
    metrics.tiles.set(GRID.n_tiles)
    with LiveServer() as server:
        url = server.url + "metrics"
        assert http.get(url).text == ""  # no scan yet
        server.metrics = metrics
        served = http.get(url)
    assert served.headers["content-type"].startswith("text/plain")
    assert "focustrack_scan_tiles 4.0" in served.text.splitlines()
