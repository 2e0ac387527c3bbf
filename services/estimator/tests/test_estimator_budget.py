"""The cost budget per slide: each strategy's cost model, kept honest against
tracemalloc, and creation refusing what exceeds the budget (real server on loopback).
The benchmarks' oracle, served on request: tests/test_estimator_serves_the_oracle.py."""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from pydantic import ValidationError

from focustrack_client import models as api
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.wire.session import free_port
from focustrack_estimator import registry
from focustrack_estimator.budget import Budget
from focustrack_estimator.errors import SlideError
from focustrack_estimator.params import resolve_params
from focustrack_estimator.service import spawn
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.slide import Slide
from focustrack_estimator.slide_strategy import cost_of
from focustrack_estimator.sqlite_store import SQLiteStore
from focustrack_estimator.strategy import Cost


def test_every_strategy_states_its_cost() -> None:
    for name in registry.STRATEGIES:
        cost = registry.SERVED.cost(name, default_settings(ScanGrid(20, 20)))
        assert cost.peak_bytes > 20 * 20 and cost.seconds_per_tile >= 0


def test_the_defaults_admit_kf_2d_on_200x200_and_refuse_the_issues_slides() -> None:
    budget = Budget.of(EstimatorSettings.model_construct())  # the defaults

    def slide(strategy: str, rows: int, cols: int, **params: object) -> api.SlideCreate:
        grid = api.Grid(rows=rows, cols=cols)
        return api.SlideCreate(strategy=strategy, grid=grid, params=params)  # type: ignore[arg-type]

    def cost(config: api.SlideCreate) -> Cost:
        params = resolve_params(config.strategy, config.params)
        return cost_of(config, params, registry.SERVED)

    def checked(config: api.SlideCreate) -> int:
        """The slide's projected peak bytes, once the budget admitted it."""
        projected = cost(config)
        budget.check(config, projected)
        return projected.peak_bytes

    assert checked(slide("kf-2d", 200, 200)) < budget.max_slide_bytes
    values = [0.1 * (i + 1) for i in range(20)]
    bank = {"sigmas_um": values, "lengths_tiles": values, "tilt_sigmas_um_per_tile": values}
    # 8000 members (unbudgeted: 41 s of CPU and 5.6 GB), the 250x750 slide, nshp at 200x200
    for config in (
        slide("kf-2d", 146, 146, **bank),
        slide("kf-2d", 250, 750),
        slide("nshp-wiener1", 200, 200),
    ):
        with pytest.raises(SlideError, match="projected to need"):
            checked(config)
    # a bank grows its cost with its members: 8000 members cost 8000/18 times 18
    small, large = cost(slide("kf-2d", 50, 50)), cost(slide("kf-2d", 50, 50, **bank))
    assert large.peak_bytes > 100 * small.peak_bytes / 4


def _measured_peak_bytes(config: api.SlideCreate, store: SQLiteStore) -> int:
    """tracemalloc's peak over a whole scan of `config` through a `Slide` (history included)."""
    store.create_slide("s", config.model_dump(mode="json"))
    tracemalloc.start()
    try:
        base_bytes = tracemalloc.get_traced_memory()[0]
        record = store.slide("s")
        assert record is not None
        slide = Slide.load(record, store, snapshot_every=10**9)
        while (acquisition := slide.next()) is not None:
            z_um = 0.3 * math.sin(acquisition.row / 5) + 0.02 * acquisition.col
            measurement = api.MeasurementIn(
                row=acquisition.row,
                col=acquisition.col,
                sequence=acquisition.index,
                z_um=z_um if acquisition.measure else None,  # an image-only tile: no z
                sigma_um=1.0,
            )
            slide.measure(measurement)
        slide.focus_map()
        return tracemalloc.get_traced_memory()[1] - base_bytes
    finally:
        tracemalloc.stop()


#: (strategy, rows, cols): each kind of cost model on a grid where its own term matters
#: (kf-2d wider than its update window, so the row prediction's copies are measured).
MEASURED = [
    ("kf-wiener0", 6, 40),
    ("kf-mmae", 6, 40),
    ("kf-2d", 3, 120),
    ("nshp-wiener1", 4, 60),
    ("survey-delaunay", 6, 40),
]


@pytest.mark.parametrize(("strategy", "rows", "cols"), MEASURED)
def test_projected_memory_is_within_a_factor_of_the_measured(
    tmp_path: Path, strategy: str, rows: int, cols: int
) -> None:
    config = api.SlideCreate(strategy=strategy, grid=api.Grid(rows=rows, cols=cols))
    store = SQLiteStore(tmp_path / "budget.sqlite")
    try:
        measured = _measured_peak_bytes(config, store)
    finally:
        store.close()
    params = resolve_params(config.strategy, config.params)
    projected = cost_of(config, params, registry.SERVED).peak_bytes
    # An estimate, not an account: within a factor of two either way of what was measured.
    assert measured / 2 <= projected <= 2 * measured, (projected, measured)


@pytest.fixture
def server(tmp_path: Path) -> Iterator[str]:
    port = free_port()
    process = spawn(tmp_path / "estimator.sqlite", port, timeout_s=120)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(30)


def _post(
    http: httpx.Client, url: str, strategy: str, rows: int, cols: int, **extra: object
) -> httpx.Response:
    body = {"strategy": strategy, "grid": {"rows": rows, "cols": cols}, **extra}
    return http.post(f"{url}/v1/slides", json=body, timeout=120)


def test_creation_refuses_slides_over_the_budget_with_the_reason(
    http: httpx.Client, server: str
) -> None:
    values = [round(0.1 * (i + 1), 1) for i in range(20)]
    bank = {"sigmas_um": values, "lengths_tiles": values, "tilt_sigmas_um_per_tile": values}
    refused = _post(http, server, "kf-2d", 146, 146, params=bank)
    assert len(refused.request.content) < 700  # a small request
    assert refused.status_code == 422, refused.text
    message = refused.json()["detail"][0]["msg"]
    assert "projected to need" in message and "--max-slide-bytes" in message
    assert _post(http, server, "kf-2d", 250, 750).status_code == 422  # the docs' whole slide
    wide = _post(http, server, "kf-2d", 250, 500)  # within the grid limits, not within the budget
    assert wide.status_code == 422 and "MiB" in wide.json()["detail"][0]["msg"]
    oracle = _post(http, server, "gp-oracle", 500, 500)  # a benchmark's floor: not served
    assert oracle.status_code == 422 and "unknown strategy" in oracle.text
    assert _post(http, server, "kf-2d", 200, 200).status_code == 201  # what a real scanner needs
    assert http.get(f"{server}/healthz").json()["slides"] == 1


def test_a_budget_that_admits_nothing_is_refused_by_the_settings() -> None:
    for name, bad in (("max_live_slides", 0), ("max_slide_bytes", -1), ("max_tile_seconds", 0.0)):
        with pytest.raises(ValidationError, match=name):
            EstimatorSettings(**{name: bad})
