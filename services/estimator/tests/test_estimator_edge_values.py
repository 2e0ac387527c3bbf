"""Odd values at the estimator's edge: non-physical sigmas and parameters are a
422 at creation, z-ranges stay within the schema's bounds whatever the steps and retries,
and no slide gets stuck on a singular matrix (real server process on loopback)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from focustrack_client import models as api
from focustrack_core.domain import ZRange
from focustrack_core.wire.session import free_port
from focustrack_estimator import strategy
from focustrack_estimator.service import spawn
from focustrack_estimator.slide import MIN_REACH_OUTSIDE_UM


@pytest.fixture(scope="module")
def estimator(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    """The server's client: one for every request (httpx's `httpx.get` makes a client per
    call, about 50 ms of CPU each for its TLS context)."""
    port = free_port()
    process = spawn(tmp_path_factory.mktemp("edge") / "edge.sqlite", port, timeout_s=120)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as client:
            yield client
    finally:
        process.terminate()
        process.wait(60)


def _create(estimator: httpx.Client, **fields: Any) -> httpx.Response:
    body = {"strategy": "kf-2d", "grid": {"rows": 4, "cols": 4}, **fields}
    return estimator.post("/v1/slides", json=body, timeout=60)


def _refused(response: httpx.Response, needle: str) -> None:
    assert response.status_code == 422, response.text
    assert needle in response.text, response.text


@pytest.mark.parametrize("name", ["start_sigma_um", "noise_sigma_um", "dof_um"])
def test_non_physical_sigmas_are_refused_at_creation(estimator: httpx.Client, name: str) -> None:
    for value in (1e-300, 0.0, -1.0):
        _refused(_create(estimator, **{name: value}), name)
    infinite = '{"strategy": "kf-2d", "grid": {"rows": 4, "cols": 4}, "' + name + '": 1e999}'
    response = estimator.post(
        "/v1/slides", content=infinite, headers={"Content-Type": "application/json"}
    )
    _refused(response, name)


def test_non_physical_parameters_are_refused_at_creation(estimator: httpx.Client) -> None:
    _refused(_create(estimator, params={"sigmas_um": [1e-300, 1.0]}), "not a physical value")
    _refused(_create(estimator, params={"window_cols": 10**200}), "not a physical value")
    _refused(
        _create(estimator, strategy="kf-wiener0", params={"q": 1e-300}), "not a physical value"
    )
    _refused(_create(estimator, params={"max_retries": 10**9}), "less than or equal to 50")
    _refused(_create(estimator, params={"lengths_tiles": [1e31]}), "less than or equal to 10000")
    _refused(_create(estimator, z_range={"z_step_um": 1e-9}), "z_step_um")


def test_a_measurement_with_a_non_physical_sigma_is_refused(estimator: httpx.Client) -> None:
    slide = _create(estimator).json()
    pending = estimator.get(f"/v1/slides/{slide['id']}/next").json()
    body = {"row": pending["row"], "col": pending["col"], "sequence": pending["sequence"]}
    for sigma_um in (1e-300, 0.0, -1.0):
        response = estimator.post(
            f"/v1/slides/{slide['id']}/measurements",
            json={**body, "z_um": 0.0, "sigma_um": sigma_um},
        )
        _refused(response, "sigma_um")


def test_z_ranges_stay_within_the_schemas_bounds(estimator: httpx.Client) -> None:
    # The largest steps and stacks the schema allows, starting at its highest height,
    # with edge peaks asking for stacks further up again and again.
    slide = _create(
        estimator,
        start_z_um=api.MAX_ABS_UM,
        start_sigma_um=api.MAX_ABS_UM,
        z_range={"z_step_um": 1e3, "min_frames": 1001, "max_frames": 1001},
        params={"max_retries": 50},
    ).json()
    for _ in range(60):
        pending = estimator.get(f"/v1/slides/{slide['id']}/next").json()
        if pending["done"]:
            break
        assert -api.MAX_ABS_UM <= pending["z_low_um"] <= pending["z_high_um"] <= api.MAX_ABS_UM
        body = {
            "row": pending["row"],
            "col": pending["col"],
            "sequence": pending["sequence"],
            "z_um": pending["z_high_um"],
            "flags": ["edge_high"],
        }
        response = estimator.post(f"/v1/slides/{slide['id']}/measurements", json=body)
        assert response.status_code == 200, response.text  # every z asked can be posted back


def test_bounded_moves_and_narrows_ranges_beyond_the_limit() -> None:
    assert strategy.bounded(ZRange(-5.0, 1.0, 11), 100.0) == ZRange(-5.0, 1.0, 11)
    assert strategy.bounded(ZRange(95.0, 1.0, 11), 100.0) == ZRange(90.0, 1.0, 11)
    assert strategy.bounded(ZRange(-120.0, 1.0, 11), 100.0) == ZRange(-100.0, 1.0, 11)
    wide = strategy.bounded(ZRange(-300.0, 100.0, 11), 100.0)
    assert (wide.low_um, wide.high_um, wide.n_frames) == (-100.0, 100.0, 3)


@pytest.mark.parametrize("name", ["kf-2d", "kf-mmae", "kf-wiener2", "nshp-wiener1"])
def test_no_slide_gets_stuck_with_the_sharpest_measurements_allowed(
    estimator: httpx.Client, name: str
) -> None:
    """Measurements as certain as the schema allows (sigma 1 nm), identical or jumping,
    never leave a slide answering errors: every tile is measured and the scan ends."""
    slide = _create(estimator, strategy=name, start_sigma_um=api.MIN_SIGMA_UM).json()
    _scan_with_sharp_jumps(estimator, slide["id"])


def _scan_with_sharp_jumps(estimator: httpx.Client, slide_id: str) -> None:
    """Scan a slide to its end with measurements as certain as the schema allows (1 nm),
    jumping between tiles as far as a stack's reading may reach, either side of it
    (`slide.MIN_REACH_OUTSIDE_UM`; farther is refused); every answer a 200, and its map too."""
    for _ in range(500):  # a few per tile at most: a slide that never ends fails the test
        pending = estimator.get(f"/v1/slides/{slide_id}/next").json()
        if pending["done"]:
            break
        body = {
            "row": pending["row"],
            "col": pending["col"],
            "sequence": pending["sequence"],
            "z_um": pending["z_low_um"] - MIN_REACH_OUTSIDE_UM
            if pending["sequence"] % 2
            else pending["z_high_um"] + MIN_REACH_OUTSIDE_UM,
            "sigma_um": api.MIN_SIGMA_UM,
        }
        response = estimator.post(f"/v1/slides/{slide_id}/measurements", json=body)
        assert response.status_code == 200, response.text
    assert pending["done"], "the scan did not end"
    assert estimator.get(f"/v1/slides/{slide_id}/map").status_code == 200


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("kf-2d", {"drift_rate_sigma_um_per_s": 1e30}),
        ("kf-2d-lean", {"drift_rate_sigma_um_per_s": 1e30}),
    ],
)
def test_parameters_that_break_the_arithmetic_together_fail_a_trial_scan(
    estimator: httpx.Client, name: str, params: dict[str, Any]
) -> None:
    """Each within the bounds, each would make a slide fail on its first sharp measurements
    ("math domain error"): refused at creation instead."""
    response = _create(estimator, strategy=name, grid={"rows": 30, "cols": 30}, params=params)
    _refused(response, "4x4 trial scan")


@pytest.mark.parametrize("name", ["kf-wiener1", "kf-wiener1-dir"])
def test_a_slope_sigma_the_smoother_once_failed_on_scans_to_its_map(
    estimator: httpx.Client, name: str
) -> None:
    """A slope sigma of 1e30 left the smoother's P- singular ("Singular matrix", refused by
    the trial scan); its pseudo-inverse carries the scan through."""
    params = {"slope_sigma_um_per_tile": 1e30}
    slide = _create(estimator, strategy=name, grid={"rows": 6, "cols": 6}, params=params).json()
    _scan_with_sharp_jumps(estimator, slide["id"])
