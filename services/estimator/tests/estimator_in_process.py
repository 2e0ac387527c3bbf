"""The estimator in process (ASGI transport) for its API tests: an app over a store,
and the calls that drive a slide through it, checked against local replays.

Every slide scanned in these tests is compared with the same strategy replayed locally
on the same measurements (`focustrack_estimator.replay`): the service must not change
a single number.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
from fastapi import FastAPI

from focustrack_client import models as api
from focustrack_core.domain import FocusMap, SlideSettings
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.app import create_app
from focustrack_estimator.event_store import open_store
from focustrack_estimator.registry import Catalogue
from focustrack_estimator.replay import replay, simulated_measurement
from focustrack_estimator.settings import EstimatorSettings

ROWS, COLS = 6, 5
SETTINGS = default_settings(ScanGrid(ROWS, COLS, pitch_um=150.0, origin_x_um=1000.0))


T = TypeVar("T")


def slide_config(strategy: str, settings: SlideSettings) -> dict[str, Any]:
    """The JSON body of `POST /v1/slides` for a slide with these settings."""
    return to_api.slide_create(strategy, settings).model_dump(mode="json")


def run(coroutine: Coroutine[Any, Any, T]) -> T:
    return asyncio.run(coroutine)


def maps(seed: int, rows: int = ROWS, cols: int = COLS) -> tuple[np.ndarray, np.ndarray]:
    """A true surface and its measurements (truth + 1.5 um noise), each (rows, cols) in um."""
    truth = generate_surfaces(SurfaceSpec(rows=rows, cols=cols), 1, seed)[0]
    return truth, truth + np.random.default_rng(seed).normal(0.0, 1.5, truth.shape)


def local_map(strategy: str, settings: SlideSettings, seed: int) -> FocusMap:
    truth, measured = maps(seed, *settings.grid.shape)
    return replay(registry.create(strategy, settings), truth, measured).focus_map


def assert_same_maps(served: FocusMap, local: FocusMap) -> None:
    names = ("prior_um", "prior_sigma_um", "posterior_um", "posterior_sigma_um", "z_used_um")
    for name in (*names, "out_of_focus_risk"):
        np.testing.assert_array_equal(getattr(served, name), getattr(local, name), err_msg=name)


@contextmanager
def estimator(
    location: Path | str, catalogue: Catalogue | None = None, **settings: Any
) -> Iterator[FastAPI]:
    """The app over the store at `location` (an SQLite file, or a PostgreSQL URL) with these
    settings, serving `catalogue` (None: the estimator's own); the store closed after."""
    store = open_store(str(location))
    try:
        yield create_app(store, EstimatorSettings(**settings), catalogue)
    finally:
        store.close()


def client(app: FastAPI, token: str | None = None) -> httpx.AsyncClient:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.AsyncClient(
        transport=httpx.ASGITransport(app), base_url="http://estimator", headers=headers
    )


async def create(http: httpx.AsyncClient, strategy: str = "kf-wiener0", **changes: Any) -> str:
    response = await http.post("/v1/slides", json={**slide_config(strategy, SETTINGS), **changes})
    assert response.status_code == 201, response.text
    return response.json()["id"]


async def scan(
    http: httpx.AsyncClient, slide_id: str, measured_um: np.ndarray, limit: int | None = None
) -> int:
    """Drive a slide through /next and /measurements (at most `limit` pairs); the pair count."""
    n_pairs = 0
    while limit is None or n_pairs < limit:
        response = await http.get(f"/v1/slides/{slide_id}/next")
        assert response.status_code == 200, response.text
        acquisition = to_domain.acquisition(api.Next.model_validate(response.json()))
        if acquisition is None:
            break
        measurement = simulated_measurement(
            acquisition, measured_um[acquisition.row, acquisition.col]
        )
        body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
        response = await http.post(f"/v1/slides/{slide_id}/measurements", json=body)
        assert response.status_code == 200, response.text
        n_pairs += 1
    return n_pairs


async def served_map(http: httpx.AsyncClient, slide_id: str) -> FocusMap:
    response = await http.get(f"/v1/slides/{slide_id}/map", params={"format": "npy"})
    assert response.status_code == 200
    return focus_map_of_npy(response.content)
