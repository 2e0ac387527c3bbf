"""A client of the estimator's REST API, and a slide served by it seen as a local `Strategy`.

`RemoteStrategy` turns a slide on an estimator service back into the two calls
every strategy answers, so anything that drives a strategy (the benchmark's
`replay`, the scheduler) drives a served slide the same way; the end-to-end
test uses that to check the service reproduces the benchmark exactly.

The JSON <-> domain conversions (`acquisition_of_next`, `measurement_body`,
`outcome_of`) are shared with the API benchmark, which speaks HTTP itself.
"""

from __future__ import annotations

import io
from typing import Any

import httpx
import numpy as np

from focustrack.services.estimator.strategy import (
    Acquisition,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    Strategy,
    ZRange,
)


def slide_config(
    strategy: str, settings: SlideSettings, params: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The body of `POST /v1/slides` for a slide with these settings."""
    grid, policy = settings.grid, settings.policy
    return {
        "strategy": strategy,
        "params": params or {},
        "grid": {
            "rows": grid.rows,
            "cols": grid.cols,
            "pitch_um": grid.pitch_um,
            "origin_x_um": grid.origin_x_um,
            "origin_y_um": grid.origin_y_um,
        },
        "start_z_um": settings.start_z_um,
        "start_sigma_um": settings.start_sigma_um,
        "dof_um": settings.dof_um,
        "noise_sigma_um": settings.noise_sigma_um,
        "z_range": {
            "k_sigma": policy.k_sigma,
            "z_step_um": policy.z_step_um,
            "min_frames": policy.min_frames,
            "max_frames": policy.max_frames,
        },
    }


def acquisition_of_next(body: dict[str, Any]) -> Acquisition | None:
    """The acquisition a `GET /next` reply describes (None when the scan is done)."""
    if body["done"]:
        return None
    return Acquisition(
        index=body["sequence"],
        row=body["row"],
        col=body["col"],
        z=ZRange(body["z_low_um"], body["z_step_um"], body["n_frames"]),
        purpose=Purpose(body["purpose"]),
        measure=body["measure"],
        predicted_um=body["predicted_z_um"],
        predicted_sigma_um=body["predicted_sigma_um"],
    )


def measurement_body(acquisition: Acquisition, measurement: Measurement) -> dict[str, Any]:
    """The body of `POST /measurements` reporting `measurement` for `acquisition`."""
    return {
        "row": acquisition.row,
        "col": acquisition.col,
        "sequence": acquisition.index,
        "z_um": measurement.z_um,
        "sigma_um": measurement.sigma_um,
        "flags": sorted(measurement.flags),
    }


def outcome_of(body: dict[str, Any]) -> Outcome:
    """The outcome a `POST /measurements` reply describes."""
    fields = (
        "prior_um",
        "prior_sigma_um",
        "posterior_um",
        "posterior_sigma_um",
        "innovation_um",
        "nis",
    )
    return Outcome(body["row"], body["col"], body["accepted"], **{f: body[f] for f in fields})


def focus_map_of_npy(content: bytes) -> FocusMap:
    """The focus map in a `GET /map?format=npy` reply (smoothed layers None when all NaN)."""
    table = np.load(io.BytesIO(content), allow_pickle=False)

    def layer(name: str) -> np.ndarray:
        return np.array(table[name])

    smoothed = {
        name: None if np.all(np.isnan(table[name])) else layer(name)
        for name in ("smoothed_um", "smoothed_sigma_um")
    }
    return FocusMap(
        prior_um=layer("prior_um"),
        prior_sigma_um=layer("prior_sigma_um"),
        posterior_um=layer("posterior_um"),
        posterior_sigma_um=layer("posterior_sigma_um"),
        z_used_um=layer("z_used_um"),
        **smoothed,
    )


class EstimatorClient:
    """Blocking client of one estimator service (`base_url` such as http://127.0.0.1:8100)."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 10.0) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout_s)

    def close(self) -> None:
        self.http.close()

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        response = self.http.request(method, path, **kwargs)
        response.raise_for_status()
        return response.json()

    def create_slide(self, config: dict[str, Any]) -> dict[str, Any]:
        return self._json("POST", "/v1/slides", json=config)

    def slide(self, slide_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/slides/{slide_id}")

    def next(self, slide_id: str) -> Acquisition | None:
        return acquisition_of_next(self._json("GET", f"/v1/slides/{slide_id}/next"))

    def measure(self, slide_id: str, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        body = measurement_body(acquisition, measurement)
        return outcome_of(self._json("POST", f"/v1/slides/{slide_id}/measurements", json=body))

    def focus_map(self, slide_id: str) -> FocusMap:
        response = self.http.get(f"/v1/slides/{slide_id}/map", params={"format": "npy"})
        response.raise_for_status()
        return focus_map_of_npy(response.content)

    def diagnostics(self, slide_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/slides/{slide_id}/diagnostics")


class RemoteStrategy(Strategy):
    """A slide on an estimator service, driven through the Strategy interface."""

    def __init__(
        self, client: EstimatorClient, slide_id: str, settings: SlideSettings, name: str
    ) -> None:
        super().__init__(settings)
        self.client, self.slide_id, self.name = client, slide_id, name

    @classmethod
    def create(
        cls,
        client: EstimatorClient,
        strategy: str,
        settings: SlideSettings,
        params: dict[str, Any] | None = None,
    ) -> RemoteStrategy:
        """A new slide on the service, scanned with `strategy`."""
        slide = client.create_slide(slide_config(strategy, settings, params))
        return cls(client, slide["id"], settings, strategy)

    def _plan(self) -> Acquisition | None:
        return self.client.next(self.slide_id)

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        return self.client.measure(self.slide_id, acquisition, measurement)

    def focus_map(self) -> FocusMap:
        return self.client.focus_map(self.slide_id)
