"""Typed strategy parameters: each strategy's model (names, defaults, bounds), validation as
JSON gives values, one resolution per slide, and the models in the OpenAPI document."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI

from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api
from focustrack_core.rest.to_domain import default_settings
from focustrack_estimator import registry
from focustrack_estimator.app import create_app
from focustrack_estimator.lean_scan import Kf2dLeanParams
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.slides import load_strategies
from focustrack_estimator.spatial import Kf2dParams, RowBankFilter
from focustrack_estimator.sqlite_store import SQLiteStore

SETTINGS = default_settings(ScanGrid(4, 5))

# The product's contract: every served strategy's parameters with their defaults.
RETRIES = {"max_retries": 3}
LEAN = {
    "risk_out_of_focus": 0.0,
    "skip_sigma_scale": 1.0,
    "skip_model_temperature": 3.0,
    "coarse_step_um": 4.0,
    "look_first": False,
    "short_frames": 3,
}
LOOP = {
    **RETRIES,
    **LEAN,
    "max_kept_planes": 1,
    "gate_nis": 0.0,
    "gate_patience": 1,
    "adapt_r": False,
    "sqrt": False,
}
TIME = {  # the time state, off by default
    "drift_walk_um2_per_s": 0.0,
    "drift_rate_sigma_um_per_s": 0.0,
    "drift_settle_tau_s": 200.0,
    "drift_rate_q_um2_per_s3": 0.0,
}
REVISITS = {**TIME, "revisit_drift_share": 0.0, "revisit_max_tiles": 3}  # kf-2d's family
DEFAULTS: dict[str, dict[str, Any]] = {
    "kf-wiener0": {**LOOP, **TIME, "q": 0.14},
    "kf-wiener1": {**LOOP, **TIME, "q": 1e-8, "q_height_um2": 0.2, "slope_sigma_um_per_tile": 0.5},
    "kf-wiener2": {
        **LOOP,
        **TIME,
        "q": 1e-10,
        "q_height_um2": 0.2,
        "slope_sigma_um_per_tile": 0.5,
        "curvature_sigma_um_per_tile2": 0.1,
    },
    "kf-gm1": {**LOOP, **TIME, "sigma": 0.7, "beta_per_tile": 8.0, "q_height_um2": 0.01},
    "kf-gm2": {
        **LOOP,
        **TIME,
        "sigma": 0.01,
        "beta_per_tile": 100.0,
        "q_height_um2": 0.2,
        "slope_sigma_um_per_tile": 0.5,
    },
    "kf-wiener1-dir": {
        **LOOP,
        **TIME,
        "q": 1e-4,
        "q_height_um2": 0.0,
        "slope_sigma_um_per_tile": 0.5,
        "partitioned": False,
    },
    "kf-mmae": {
        **LOOP,
        "gate_nis": 25.0,
        "q": 1e-4,
        "q_spread": 3.0,
        "q_height_um2": 0.3,
        "weight_floor": 1e-3,
        "nis_clip": 9.0,
    },
    "kf-2d": {
        **RETRIES,
        **REVISITS,
        "sigmas_um": [0.7, 1.4, 2.8],
        "lengths_tiles": [4.0, 8.0, 16.0],
        "tilt_sigmas_um_per_tile": [0.3, 1.5],
        "window_cols": 12,
        "prune_log_weight": 20.0,
        "smooth_block_cols": 16,
        "smooth_margin_cols": 8,
    },
    "nshp-wiener0": {**RETRIES, "support": 1, "q_um2": 0.5},
    "nshp-wiener1": {**RETRIES, "support": 2, "q_um2": 0.03},
    "kf-2d-lean": {
        **RETRIES,
        **LEAN,
        **REVISITS,
        "risk_out_of_focus": 0.01,
        "max_kept_planes": 5,
    },
    "kf-2d-laser": {
        **RETRIES,
        **LEAN,
        "risk_out_of_focus": 0.01,
        "skip_model_temperature": 1.0,
        "max_kept_planes": 5,
        "laser_sigma_um": 0.05,
        "laser_reading_s": 0.001,
        "offset_um": 4.0,
        "offset_sigma_um": 0.4,
        "sigmas_um": [0.7, 1.4, 2.8],
        "lengths_tiles": [4.0, 8.0, 16.0],
        "tilt_sigmas_um_per_tile": [0.03, 0.3],
        "window_cols": 12,
        "prune_log_weight": 20.0,
        "smooth_block_cols": 16,
        "smooth_margin_cols": 8,
    },
    "kf-rescan": {
        **LOOP,
        "risk_out_of_focus": 0.01,
        "max_kept_planes": 5,
        "prior_map_um": [],
        "prior_map_sigma_um": [],
        "local_sigma_um": 0.05,
        "rate_sigma_um_per_s": 0.05,
        "rate_q_um2_per_s3": 1e-6,
        "offset_q_um2_per_s": 0.0,
    },
    "af-every-tile": {},
    "tile-skip": {"every": 2},
    "survey-bilinear": {"n_survey": 36},
    "survey-spline": {"n_survey": 81},
    "survey-delaunay": {"n_survey": 36},
}


def test_every_strategy_has_its_parameters_with_their_defaults() -> None:
    assert list(registry.STRATEGIES) == list(DEFAULTS)  # the benchmark's order too
    for name, defaults in DEFAULTS.items():
        served = registry.parameters(name)
        assert served == defaults, name
        # JSON types as well: a float default stays a float (1.0, not 1)
        assert {k: type(v) for k, v in served.items()} == {
            k: type(v) for k, v in defaults.items()
        }, name


@pytest.mark.parametrize("name", sorted(DEFAULTS))
def test_defaults_survive_a_round_trip_through_json(name: str) -> None:
    """A slide's stored config (every parameter resolved, as JSON) resolves to the same."""
    defaults = registry.SERVED.params(name)
    assert registry.SERVED.params(name, defaults.model_dump(mode="json")) == defaults


def test_values_are_taken_as_json_gives_them() -> None:
    params = registry.SERVED.params("kf-2d", {"prune_log_weight": 5, "sigmas_um": [1, 2.5]})
    assert isinstance(params, Kf2dParams)
    assert params.prune_log_weight == 5.0 and isinstance(params.prune_log_weight, float)
    assert params.sigmas_um == (1.0, 2.5)  # a list of numbers for a bank's tuple
    assert params.model_dump(mode="json")["sigmas_um"] == [1.0, 2.5]
    # null asks for the default, whatever the default is
    assert registry.SERVED.params("kf-2d", {"window_cols": None}).window_cols == 12


@pytest.mark.parametrize(
    ("name", "values", "needle"),
    [
        ("kf-wiener0", {"qq": 1.0}, "unknown parameter 'qq' for strategy 'kf-wiener0'; known: "),
        ("kf-wiener0", {"qq": None}, "unknown parameter 'qq'"),
        ("kf-wiener0", {"q": True}, "parameter 'q' of strategy 'kf-wiener0' (default 0.14)"),
        ("kf-wiener0", {"max_retries": True}, "valid integer"),
        ("kf-wiener0", {"max_retries": 3.0}, "valid integer"),
        ("kf-wiener0", {"adapt_r": 1}, "valid boolean"),
        ("kf-wiener0", {"q": float("nan")}, "finite number"),
        ("kf-wiener0", {"q": 1e-40}, "not a physical value"),
        ("kf-wiener0", {"q": -1.0}, "greater than or equal to 0"),
        ("kf-wiener0", {"max_retries": 51}, "less than or equal to 50"),
        ("kf-2d", {"sigmas_um": []}, "at least 1 item"),
        ("kf-2d", {"sigmas_um": [1.0, 0.0]}, "greater than 0"),
        ("kf-2d", {"lengths_tiles": [1e31]}, "less than or equal to 10000"),
        ("kf-2d", {"window_cols": 10**200}, "not a physical value"),
        ("kf-2d-lean", {"risk_out_of_focus": 1.0}, "less than 1"),
        ("kf-2d-lean", {"coarse_step_um": 1e30}, "less than or equal to 1000"),
        ("kf-2d-lean", {"gate_nis": 9.0}, "unknown parameter 'gate_nis'"),
        ("kf-gm1", {"beta_per_tile": 2.0}, "beta >= 5.98"),
        ("kf-mmae", {"weight_floor": 0.25}, "less than 0.25"),
        ("tile-skip", {"every": 0}, "greater than or equal to 1"),
    ],
)
def test_a_refusal_names_the_parameter_and_why(
    name: str, values: dict[str, Any], needle: str
) -> None:
    with pytest.raises(registry.ParamsError, match="'" + next(iter(values)) + "'") as refused:
        registry.create(name, SETTINGS, values)
    assert needle in str(refused.value)
    assert refused.value.name == next(iter(values))


def test_a_model_of_another_strategy_is_refused() -> None:
    with pytest.raises(TypeError, match="Kf2dLeanParams"):
        registry.create("kf-2d-lean", SETTINGS, Kf2dParams())


def test_kf_2d_lean_is_kf_2d_with_its_own_loop_options_from_construction_on() -> None:
    params = {"max_retries": 1, "risk_out_of_focus": 0.2, "max_kept_planes": 3}
    lean = registry.create("kf-2d-lean", SETTINGS, params)
    plain = registry.create("kf-2d", SETTINGS)
    assert isinstance(lean, RowBankFilter) and isinstance(plain, RowBankFilter)
    assert (lean.name, plain.name) == ("kf-2d-lean", "kf-2d")
    assert lean._search.max_retries == 1  # the peak search built in __init__
    assert lean.stated_risk == 0.2 and lean.options.max_kept_planes == 3
    assert plain.stated_risk is None and plain.options.max_kept_planes == 1
    assert [m.sigma_um for m in lean.models] == [m.sigma_um for m in plain.models]


# --- the REST API --------------------------------------------------------------------------


@pytest.fixture
def app(tmp_path: Path) -> Iterator[FastAPI]:
    store = SQLiteStore(tmp_path / "estimator.sqlite")
    yield create_app(store, EstimatorSettings())
    store.close()


def _request(app: FastAPI, method: str, path: str, **kwargs: Any) -> httpx.Response:
    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app)
        async with httpx.AsyncClient(transport=transport, base_url="http://estimator") as http:
            return await http.request(method, path, **kwargs)

    return asyncio.run(go())


def _body(strategy: str, params: dict[str, Any]) -> dict[str, Any]:
    body = to_api.slide_create(strategy, SETTINGS).model_dump(mode="json")
    return {**body, "params": params}


def test_the_openapi_document_has_each_strategys_parameters() -> None:
    load_strategies()  # as the service does a moment after it starts
    store = SQLiteStore(":memory:")
    try:
        schemas = create_app(store, EstimatorSettings()).openapi()["components"]["schemas"]
    finally:
        store.close()
    risk = schemas["Kf2dLeanParams"]["properties"]["risk_out_of_focus"]
    assert "number" in risk["type"] and risk["default"] == 0.01
    assert (risk["minimum"], risk["exclusiveMaximum"]) == (0.0, 1.0)
    assert "depth of field" in risk["description"]
    window = schemas["Kf2dParams"]["properties"]["window_cols"]
    assert "integer" in window["type"] and window["minimum"] == 1 and window["default"] == 12
    assert schemas["Kf2dParams"]["additionalProperties"] is False
    params = schemas["SlideCreate"]["properties"]["params"]
    assert {"$ref": "#/components/schemas/Kf2dLeanParams"} in params["anyOf"]
    assert params["x-strategy-params"]["kf-2d"] == {"$ref": "#/components/schemas/Kf2dParams"}
    assert "strategy" in params["description"]
    assert set(params["x-strategy-params"]) == set(registry.STRATEGIES)


def test_strategies_are_listed_with_their_schemas_and_defaults(app: FastAPI) -> None:
    response = _request(app, "GET", "/v1/strategies")
    assert response.status_code == 200, response.text
    listed = {info["name"]: info for info in response.json()}
    assert set(listed) == set(registry.STRATEGIES)
    for name, info in listed.items():
        assert info["defaults"] == registry.parameters(name)
        assert set(info["parameters"]["properties"]) == set(info["defaults"])
    assert listed["kf-2d-lean"]["parameters"]["title"] == Kf2dLeanParams.__name__


@pytest.mark.parametrize(
    ("strategy", "params", "name"),
    [
        ("kf-wiener0", {"q": "big"}, "q"),
        ("kf-wiener0", {"max_retries": True}, "max_retries"),
        ("kf-2d-lean", {"risk_out_of_focus": 1.5}, "risk_out_of_focus"),
        ("kf-2d", {"sigmas_um": [1e-300, 1.0]}, "sigmas_um"),
        ("kf-wiener0", {"qq": 1.0}, "qq"),
    ],
)
def test_a_bad_parameter_is_a_422_located_at_it(
    app: FastAPI, strategy: str, params: dict[str, Any], name: str
) -> None:
    response = _request(app, "POST", "/v1/slides", json=_body(strategy, params))
    assert response.status_code == 422, response.text
    (detail,) = response.json()["detail"]
    assert detail["loc"] == ["body", "params", name]
    assert name in detail["msg"] and strategy in detail["msg"]


def test_the_served_slide_has_every_parameter_resolved_as_json(app: FastAPI) -> None:
    body = _body("kf-2d", {"prune_log_weight": 5, "sigmas_um": [1, 2], "window_cols": None})
    created = _request(app, "POST", "/v1/slides", json=body)
    assert created.status_code == 201, created.text
    assert created.json()["config"]["params"] == {
        **DEFAULTS["kf-2d"],
        "prune_log_weight": 5.0,
        "sigmas_um": [1.0, 2.0],
    }
    assert isinstance(created.json()["config"]["params"]["prune_log_weight"], float)


def test_a_slide_stored_by_the_previous_version_loads(app: FastAPI) -> None:
    """Its config holds every parameter resolved, as JSON: it is read with the models."""
    config = {**_body("kf-2d-lean", DEFAULTS["kf-2d-lean"]), "label": None}
    app.state.slides.store.create_slide("old", config)
    response = _request(app, "GET", "/v1/slides/old/next")
    assert response.status_code == 200, response.text
    assert response.json()["done"] is False


def test_an_unknown_parameter_is_answered_with_every_known_one(app: FastAPI) -> None:
    """The list used to be cut at 200 characters, as a quoted input is."""
    response = _request(app, "POST", "/v1/slides", json=_body("kf-2d-laser", {"qq": 1.0}))
    assert response.status_code == 422, response.text
    (detail,) = response.json()["detail"]
    known = registry.STRATEGIES["kf-2d-laser"].params.model_fields
    assert len(", ".join(known)) > 200 and "(cut: " not in detail["msg"]
    assert detail["msg"].endswith(f"known: {', '.join(known)}")


@pytest.mark.parametrize(
    ("value", "loc", "msg"),
    [
        ("NaN", ["body", "params", "q"], "Input should be a finite number"),
        ('{"a": 1}', ["body", "params", "q"], "Input should be a number, a boolean, a string"),
        ('[1, "x"]', ["body", "params", "q", 1], "Input should be a valid number"),
    ],
)
def test_a_parameter_of_no_value_type_is_one_error_at_it(
    app: FastAPI, value: str, loc: list[Any], msg: str
) -> None:
    """It was five, one per type a parameter may have (``params.q.bool``, ``.int``, ...)."""
    body = json.dumps(_body("kf-wiener0", {})).replace(
        '"params": {}', f'"params": {{"q": {value}}}'
    )
    response = _request(
        app, "POST", "/v1/slides", content=body, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422, response.text
    (detail,) = response.json()["detail"]
    assert detail["loc"] == loc and detail["msg"].startswith(msg)
