"""The estimator as deployed: a real uvicorn process on loopback, a real SQLite file.

A full 20x20 scan through HTTP, driven by the benchmark's own replay loop
(`remote_strategy.RemoteStrategy`, beside this test, makes the served slide look like a
local strategy), must give exactly the benchmark's scores; a scan whose server is killed
with SIGKILL in the middle and restarted on the same store must finish identically.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path
from subprocess import Popen

import numpy as np
import pytest
from remote_strategy import RemoteStrategy

from focustrack_client import EstimatorClient
from focustrack_core.domain import Acquisition, Measurement, Outcome
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_core.wire.session import free_port
from focustrack_estimator import registry
from focustrack_estimator.replay import replay, score
from focustrack_estimator.service import spawn
from focustrack_estimator.sqlite_store import SQLiteStore

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

SEED = 1234
#: Seconds a server may take to start: imports alone took 30-45 s on a loaded 2-core machine.
START_TIMEOUT_S = 120.0
SETTINGS = default_settings(ScanGrid(20, 20))


def standard_map(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A standard 20x20 surface and its measurements (1.5 um noise), in um."""
    truth = generate_surfaces(SurfaceSpec(), 1, seed)[0]
    return truth, truth + np.random.default_rng(seed).normal(0.0, 1.5, truth.shape)


class Server:
    """The estimator in a child process, restartable on the same store and port."""

    def __init__(self, store: Path) -> None:
        self.store, self.port = store, free_port()
        self.process: Popen = spawn(store, self.port, timeout_s=START_TIMEOUT_S)
        self.url = f"http://127.0.0.1:{self.port}"

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)  # no shutdown, no checkpoint, no flush
        self.process.wait(timeout=10)

    def restart(self) -> None:
        self.process = spawn(self.store, self.port, timeout_s=START_TIMEOUT_S)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One server for the module (starting one takes seconds); tests may kill and restart it."""
    server = Server(tmp_path_factory.mktemp("estimator") / "estimator.sqlite")
    yield server
    server.stop()


@pytest.mark.parametrize("strategy", ["kf-wiener1-dir", "survey-delaunay"])
def test_a_full_scan_over_http_scores_as_the_benchmark(server: Server, strategy: str) -> None:
    truth, measured = standard_map(SEED)
    local = replay(registry.create(strategy, SETTINGS), truth, measured)
    client = EstimatorClient(server.url)
    served = RemoteStrategy.create(client, strategy, SETTINGS)
    remote = replay(served, truth, measured)

    assert score([remote], SETTINGS.dof_um) == score([local], SETTINGS.dof_um)
    assert remote.outcomes == local.outcomes
    assert (remote.n_images, remote.scan_time_s) == (local.n_images, local.scan_time_s)
    slide = client.slide(served.slide_id)
    assert slide.done and slide.n_acquisitions == len(local.outcomes)
    client.close()


class _KilledMidScan(RemoteStrategy):
    """A remote slide whose server is SIGKILLed right after acquisition `kill_after` is recorded."""

    def __init__(self, server: Server, kill_after: int, strategy: str) -> None:
        client = EstimatorClient(server.url)
        self.server, self.kill_after, self.restarted = server, kill_after, False
        slide = client.create_slide(to_api.slide_create(strategy, SETTINGS))
        super().__init__(client, slide.id, SETTINGS, strategy)

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        outcome = super()._take(acquisition, measurement)
        if acquisition.index == self.kill_after:
            self.server.kill()
            self.server.restart()
            self.client.close()
            self.client = EstimatorClient(self.server.url)
            # The reply came after the commit: the restarted service has every measurement.
            assert self.client.slide(self.slide_id).n_acquisitions == self.kill_after + 1
            self.restarted = True
        return outcome


def test_a_killed_and_restarted_service_loses_nothing(server: Server) -> None:
    truth, measured = standard_map(SEED + 1)
    strategy = "kf-wiener0"
    local = replay(registry.create(strategy, SETTINGS), truth, measured)
    remote_strategy = _KilledMidScan(server, kill_after=157, strategy=strategy)
    remote = replay(remote_strategy, truth, measured)

    assert remote_strategy.restarted
    assert remote.outcomes == local.outcomes
    assert score([remote], SETTINGS.dof_um) == score([local], SETTINGS.dof_um)
    for name in ("prior_um", "prior_sigma_um", "posterior_um", "posterior_sigma_um", "z_used_um"):
        np.testing.assert_array_equal(
            getattr(remote.focus_map, name), getattr(local.focus_map, name), err_msg=name
        )
    remote_strategy.client.close()


@pytest.mark.slow
def test_kf_2d_killed_restarts_from_its_snapshot_and_loses_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With a snapshot every 50 measurements a kill -9 after 157 replays only the last 7."""
    monkeypatch.setenv("FOCUSTRACK_ESTIMATOR_SNAPSHOT_EVERY", "50")
    server = Server(tmp_path / "estimator.sqlite")
    try:
        truth, measured = standard_map(SEED + 2)
        local = replay(registry.create("kf-2d", SETTINGS), truth, measured)
        remote_strategy = _KilledMidScan(server, kill_after=157, strategy="kf-2d")
        remote = replay(remote_strategy, truth, measured)
        assert remote_strategy.restarted
        assert remote.outcomes == local.outcomes
        np.testing.assert_array_equal(remote.focus_map.smoothed_um, local.focus_map.smoothed_um)
        remote_strategy.client.close()
        server.stop()  # a clean shutdown: the scan is complete, its snapshot covers it all
        store = SQLiteStore(server.store)
        snapshot = store.snapshot(remote_strategy.slide_id)
        store.close()
        assert snapshot is not None and snapshot[0] == len(local.outcomes)
    finally:
        server.stop()
