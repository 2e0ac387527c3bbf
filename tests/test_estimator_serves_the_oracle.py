"""The benchmarks' oracle on the estimator: `gp-oracle` is served only when the
service is started with `--strategies-from focustrack.bench.strategies`, and then within the
cost budget like any strategy (a real server on loopback). The estimator alone:
services/estimator/tests/test_estimator_budget.py."""

from __future__ import annotations

from pathlib import Path

import httpx

from focustrack.bench.strategies import CATALOGUE
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.wire.session import free_port
from focustrack_estimator import registry
from focustrack_estimator.service import spawn


def test_the_benchmarks_catalogue_states_every_cost() -> None:
    assert set(CATALOGUE.strategies) > set(registry.STRATEGIES)
    cost = CATALOGUE.cost("gp-oracle", default_settings(ScanGrid(20, 20)))
    assert cost.peak_bytes > 20 * 20 and cost.seconds_per_tile >= 0


def _post(http: httpx.Client, url: str, rows: int, cols: int) -> httpx.Response:
    body = {"strategy": "gp-oracle", "grid": {"rows": rows, "cols": cols}}
    return http.post(f"{url}/v1/slides", json=body, timeout=120)


def test_gp_oracle_is_served_only_when_opted_into_and_within_the_budget(
    http: httpx.Client, tmp_path: Path
) -> None:
    port = free_port()
    options = ["--strategies-from", "focustrack.bench.strategies"]
    process = spawn(tmp_path / "oracle.sqlite", port, timeout_s=120, options=options)
    url = f"http://127.0.0.1:{port}"
    try:
        assert _post(http, url, 10, 10).status_code == 201
        for rows, cols in ((90, 90), (500, 500)):  # 1 GB and 466 GiB slides
            refused = _post(http, url, rows, cols)
            assert refused.status_code == 422 and "projected to need" in refused.text
    finally:
        process.terminate()
        process.wait(60)
