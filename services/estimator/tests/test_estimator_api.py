"""The estimator's REST API in process (ASGI transport): behaviour, validation, concurrency.

Every slide scanned here is checked against the same strategy replayed locally
on the same measurements (`focustrack_estimator.replay`): the service must not
change a single number. Restarts on a store: test_estimator_restart.py.
"""

from __future__ import annotations

import asyncio
import io
import json
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from estimator_in_process import (
    COLS,
    ROWS,
    SETTINGS,
    assert_same_maps,
    client,
    create,
    estimator,
    local_map,
    maps,
    run,
    scan,
    served_map,
    slide_config,
)
from fastapi import FastAPI

from focustrack_client import models as api
from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import MAP_LAYERS, focus_map_of_npy
from focustrack_core.rest import to_api, to_domain
from focustrack_core.rest.to_domain import default_settings
from focustrack_estimator import registry
from focustrack_estimator.replay import replay, simulated_measurement


def test_create_list_get_delete(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            first = await create(http, "kf-wiener1-dir", params={"q": 0.01}, label="slide 7")
            second = await create(http, "survey-delaunay")
            listed = await http.get("/v1/slides")
            assert [s["id"] for s in listed.json()] == [first, second]
            assert "link" not in listed.headers and "x-next-cursor" not in listed.headers
            slide = (await http.get(f"/v1/slides/{first}")).json()
            # Omitted parameters are resolved to the strategy's defaults, and stored.
            assert slide["config"]["params"] == {
                **registry.parameters("kf-wiener1-dir"),
                "q": 0.01,
            }
            assert slide["config"]["label"] == "slide 7"
            assert (slide["n_acquisitions"], slide["done"]) == (0, False)
            assert (await http.delete(f"/v1/slides/{first}")).status_code == 204
            assert (await http.get(f"/v1/slides/{first}")).status_code == 404
            assert (await http.get(f"/v1/slides/{first}/next")).status_code == 404
            assert (await http.delete(f"/v1/slides/{first}")).status_code == 404
            assert [s["id"] for s in (await http.get("/v1/slides")).json()] == [second]

    run(go())


def test_next_is_stable_and_placed_on_the_stage(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            _, measured = maps(1)
            await scan(http, slide_id, measured, limit=7)  # row 1, going right to left
            first = (await http.get(f"/v1/slides/{slide_id}/next")).json()
            assert (await http.get(f"/v1/slides/{slide_id}/next")).json() == first
            assert first["sequence"] == 7
            assert (first["row"], first["col"]) == (1, COLS - 1 - (7 - COLS))
            assert first["stage_x_um"] == 1000.0 + 150.0 * first["col"]
            assert first["stage_y_um"] == 150.0 * first["row"]
            assert first["z_low_um"] < first["predicted_z_um"] < first["z_high_um"]
            assert first["z_high_um"] - first["z_low_um"] == pytest.approx(
                (first["n_frames"] - 1) * first["z_step_um"]
            )
            assert first["purpose"] == "scan" and first["measure"] is True

    run(go())


def test_idempotent_repost_and_conflicting_values(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            url = f"/v1/slides/{slide_id}/measurements"
            body = {"row": 0, "col": 0, "sequence": 0, "z_um": 1.25, "sigma_um": 1.0}
            first = await http.post(url, json=body)
            again = await http.post(url, json=body)
            assert first.status_code == again.status_code == 200
            assert first.json() == again.json()
            outcome = first.json()
            assert outcome["accepted"] and outcome["innovation_um"] == 1.25
            assert outcome["prior_um"] == 0.0 and outcome["prior_sigma_um"] == 10.0
            assert outcome["nis"] == pytest.approx(1.25**2 / (10.0**2 + 1.0**2))
            slide = (await http.get(f"/v1/slides/{slide_id}")).json()
            assert slide["n_acquisitions"] == 1  # the re-post recorded nothing

            changed = await http.post(url, json={**body, "z_um": 1.5})
            assert changed.status_code == 409 and "already recorded" in changed.json()["detail"]
            assert '{"z_um": 1.25, "sigma_um": ' in changed.json()["detail"]  # JSON, no reprs
            moved = await http.post(url, json={**body, "col": 1})
            assert moved.status_code == 409

    run(go())


def _slide_body(**changes: Any) -> dict[str, Any]:
    return {**slide_config("kf-wiener0", SETTINGS), **changes}


def _grid(**changes: Any) -> dict[str, Any]:
    return {"rows": ROWS, "cols": COLS, **changes}


# (case, method, path under the slide or None for /v1/slides, body, status, text in the detail)
INVALID = [
    ("unknown strategy", "post", None, _slide_body(strategy="kf-nope"), 422, "unknown strategy"),
    ("unknown parameter", "post", None, _slide_body(params={"qq": 1.0}), 422, "qq"),
    ("parameter type", "post", None, _slide_body(params={"q": "big"}), 422, "a valid number"),
    ("bool for int", "post", None, _slide_body(params={"max_retries": True}), 422, "int"),
    ("unknown field", "post", None, _slide_body(colour="red"), 422, "colour"),
    ("prior map beyond the API's heights", "post", None,
     {**slide_config("kf-rescan", SETTINGS), "params": {"prior_map_um": [1e30] * ROWS * COLS}},
     422, "prior_map_um"),
    ("kept planes beyond a stack's frames", "post", None,
     {**slide_config("kf-2d-lean", SETTINGS), "params": {"max_kept_planes": 10**6}}, 422,
     "max_kept_planes"),
    ("bank length beyond any slide", "post", None,
     _slide_body(strategy="kf-2d", params={"lengths_tiles": [4.0, 1e29]}), 422, "10000"),
    ("grid too large", "post", None, _slide_body(grid=_grid(rows=1000, cols=1000)), 422, "tiles"),
    ("empty grid", "post", None, _slide_body(grid=_grid(rows=0)), 422, "rows"),
    ("negative pitch", "post", None, _slide_body(grid=_grid(pitch_um=-1)), 422, "pitch_um"),
    (
        "frames order",
        "post",
        None,
        _slide_body(z_range={"min_frames": 9, "max_frames": 5}),
        422,
        "min_frames",
    ),
    ("negative start sigma", "post", None, _slide_body(start_sigma_um=-2), 422, "start_sigma"),
    ("outside grid", "post", "measurements", {"row": 9, "col": 0, "sequence": 0, "z_um": 1}, 422,
     "outside"),
    ("tile not asked for", "post", "measurements", {"row": 0, "col": 3, "sequence": 0, "z_um": 1},
     409, "not asked for"),
    ("sequence not asked for", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 5, "z_um": 1}, 409, "pending one is 0"),
    ("negative sigma", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 0, "z_um": 1, "sigma_um": -0.5}, 422, "sigma_um"),
    ("zero sigma", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 0, "z_um": 1, "sigma_um": 0}, 422, "sigma_um"),
    ("both edges", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 0, "z_um": 1, "flags": ["edge_low", "edge_high"]}, 422,
     "contradict each other"),
    ("unknown flag", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 0, "z_um": 1, "flags": ["blurry"]}, 422, "flags"),
    ("missing z", "post", "measurements", {"row": 0, "col": 0, "sequence": 0}, 422, "z_um"),
    ("huge z", "post", "measurements", {"row": 0, "col": 0, "sequence": 0, "z_um": 1e300}, 422,
     "z_um"),
    # a height in nm for um was taken, and the next tiles' stacks went 2 mm away
    ("z far outside its stack", "post", "measurements",
     {"row": 0, "col": 0, "sequence": 0, "z_um": 2000}, 422, "um outside the stack of"),
    ("unknown map format", "get", "map?format=tiff", None, 422, "format"),
    # these answered JSON: a misspelt parameter was left at its default, a second one won
    ("misspelt map format", "get", "map?fromat=png", None, 422,
     "'loc': ['query', 'fromat'], 'msg': 'unknown query parameter; this route takes format'"),
    ("map format twice", "get", "map?format=png&format=npy", None, 422,
     "'loc': ['query', 'format'], 'msg': 'given more than once"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("method", "where", "body", "status", "text"),
    [case[1:] for case in INVALID],
    ids=[case[0] for case in INVALID],
)
def test_bad_input_gets_a_4xx_naming_the_problem(
    app: FastAPI, method: str, where: str | None, body: Any, status: int, text: str
) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            url = "/v1/slides" if where is None else f"/v1/slides/{slide_id}/{where}"
            response = await http.request(method.upper(), url, json=body)
            assert response.status_code == status, response.text
            assert text in str(response.json()["detail"])

    run(go())


def test_a_body_not_sent_as_json_is_a_415_that_says_so(app: FastAPI) -> None:
    """curl's -d sends a form's media type; FastAPI alone said the body was no object."""

    async def go() -> None:
        async with client(app) as http:
            form = {"Content-Type": "application/x-www-form-urlencoded"}
            created = await http.post("/v1/slides", content=_json(_slide_body()), headers=form)
            assert created.status_code == 415, created.text
            assert created.json()["detail"].startswith("the body is JSON, sent as application/json")
            slide_id = await create(http)
            measured = await http.post(
                f"/v1/slides/{slide_id}/measurements",
                content=_json({"row": 0, "col": 0, "sequence": 0, "z_um": 1.0}),
                headers={"Content-Type": "text/plain"},
            )
            assert measured.status_code == 415 and "text/plain" in measured.text
            untyped = await http.post(
                f"/v1/slides/{slide_id}/measurements",
                content=_json({"row": 0, "col": 0, "sequence": 0, "z_um": 1.0}),
            )
            assert untyped.status_code == 415 and "no Content-Type" in untyped.text

    run(go())


def test_a_height_for_a_tile_only_to_be_imaged_is_refused(app: FastAPI) -> None:
    """It was taken (200, accepted false) and dropped unseen."""

    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http, "survey-bilinear")
            for _ in range(ROWS * COLS * 3):
                pending = (await http.get(f"/v1/slides/{slide_id}/next")).json()
                assert not pending["done"]
                body = {key: pending[key] for key in ("row", "col", "sequence")}
                if not pending["measure"]:
                    break
                response = await http.post(
                    f"/v1/slides/{slide_id}/measurements", json={**body, "z_um": 0.5}
                )
                assert response.status_code == 200, response.text
            url = f"/v1/slides/{slide_id}/measurements"
            refused = await http.post(url, json={**body, "z_um": 1.23})
            assert refused.status_code == 422, refused.text
            assert "measure: false" in refused.text and "z_um" in refused.text
            assert (await http.post(url, json={**body, "z_um": None})).status_code == 200

    run(go())


def test_the_last_measurement_is_acknowledged_when_the_final_map_fails(app: FastAPI) -> None:
    """It was stored, then answered with a 422 (the final smoother's "Singular matrix"):
    a client told nothing was recorded drops a measurement the log holds. No value the
    API takes makes that map fail now, so the failure is injected."""

    def failing_map() -> FocusMap:
        raise np.linalg.LinAlgError("Singular matrix")

    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            await scan(http, slide_id, maps(3)[1], limit=1)
            app.state.slides._live[slide_id].strategy.focus_map = failing_map
            await scan(http, slide_id, maps(3)[1])  # each post answered 200
            assert (await http.get(f"/v1/slides/{slide_id}")).json()["done"] is True

    run(go())


def test_a_method_the_path_does_not_take_is_a_405_with_its_own_code(app: FastAPI) -> None:
    """The client raises on the code: a wrong method is no unknown slide."""

    async def go() -> None:
        async with client(app) as http:
            refused = await http.delete("/v1/slides")
            assert refused.status_code == 405, refused.text
            assert refused.json()["code"] == "method_not_allowed"
            assert set(refused.headers["Allow"].split(", ")) == {"GET", "POST"}

    run(go())


def _json(body: dict[str, Any]) -> bytes:
    return json.dumps(body).encode()


def test_a_stack_of_kept_planes_stays_within_the_slides_frames(app: FastAPI) -> None:
    """max_kept_planes above the slide's max_frames once asked for a stack of that many
    frames (999,999 after a wild measurement); a planes stack is a stack, within bounds."""

    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http, "kf-2d-lean", params={"max_kept_planes": 1001})
            # the second, wild but within its stack's reach (`slide.MIN_REACH_OUTSIDE_UM`), is kept
            for z_um, sigma_um in ((30.0, 0.5), (79.0, 0.001)):
                step = (await http.get(f"/v1/slides/{slide_id}/next")).json()
                where = {key: step[key] for key in ("row", "col", "sequence")}
                measurement = {**where, "z_um": z_um, "sigma_um": sigma_um}
                posted = await http.post(f"/v1/slides/{slide_id}/measurements", json=measurement)
                assert posted.status_code == 200, posted.text
            step = (await http.get(f"/v1/slides/{slide_id}/next")).json()
            assert step["purpose"] == "planes", step
            assert step["n_frames"] == SETTINGS.policy.max_frames, step

    run(go())


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_are_refused(app: FastAPI, literal: str) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            content = f'{{"row": 0, "col": 0, "sequence": 0, "z_um": {literal}}}'
            response = await http.post(
                f"/v1/slides/{slide_id}/measurements",
                content=content,
                headers={"Content-Type": "application/json"},
            )
            assert response.status_code == 422
            assert response.json()["detail"][0]["loc"] == ["body", "z_um"]
            assert "finite" in response.json()["detail"][0]["msg"]

    run(go())


def test_unknown_slide_and_oversized_body(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            response = await http.get("/v1/slides/0123abcd/next")
            assert response.status_code == 404 and "0123abcd" in response.json()["detail"]
            oversized = {**_slide_body(), "label": "x" * 100, "params": {}}
            oversized["pad"] = "x" * 100_000
            response = await http.post("/v1/slides", json=oversized)
            assert response.status_code == 413 and "exceeds" in response.json()["detail"]

            async def chunks() -> Any:  # no Content-Length: counted as it streams in
                for _ in range(100):
                    yield b" " * 1024

            response = await http.post(
                "/v1/slides", content=chunks(), headers={"Content-Type": "application/json"}
            )
            assert response.status_code == 413 and "exceeds" in response.json()["detail"]

    run(go())


def test_edge_peak_asks_again_beyond_the_edge(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http, z_range={"min_frames": 5, "max_frames": 11})
            first = (await http.get(f"/v1/slides/{slide_id}/next")).json()
            body = {"row": 0, "col": 0, "sequence": 0, "z_um": None, "flags": ["edge_high"]}
            outcome = (await http.post(f"/v1/slides/{slide_id}/measurements", json=body)).json()
            assert outcome["accepted"] is False and outcome["posterior_um"] is None
            retry = (await http.get(f"/v1/slides/{slide_id}/next")).json()
            assert (retry["row"], retry["col"], retry["sequence"]) == (0, 0, 1)
            assert retry["purpose"] == "retry"
            assert retry["z_low_um"] < first["z_high_um"] < retry["z_high_um"]  # past the edge
            diagnostics = (await http.get(f"/v1/slides/{slide_id}/diagnostics")).json()
            assert (diagnostics["n_measured"], diagnostics["n_rejected"]) == (1, 1)

    run(go())


def test_finished_scan_says_done_and_refuses_more(app: FastAPI) -> None:
    settings = default_settings(ScanGrid(2, 2))

    async def go() -> None:
        async with client(app) as http:
            response = await http.post("/v1/slides", json=slide_config("tile-skip", settings))
            slide_id = response.json()["id"]
            _, measured = maps(3, 2, 2)
            await scan(http, slide_id, measured)
            assert (await http.get(f"/v1/slides/{slide_id}/next")).json() == {
                **{key: None for key in (await http.get("/openapi.json")).json()["components"][
                    "schemas"]["Next"]["properties"]},
                "done": True,
            }  # fmt: skip
            slide = (await http.get(f"/v1/slides/{slide_id}")).json()
            assert slide["done"] is True
            body = {"row": 0, "col": 0, "sequence": slide["n_acquisitions"], "z_um": 0.0}
            response = await http.post(f"/v1/slides/{slide_id}/measurements", json=body)
            assert response.status_code == 409 and "complete" in response.json()["detail"]

    run(go())


def test_concurrent_requests_on_one_slide_are_serialised(app: FastAPI) -> None:
    async def go() -> None:
        async with client(app) as http:
            slide_id = await create(http)
            url = f"/v1/slides/{slide_id}/measurements"
            body = {"row": 0, "col": 0, "sequence": 0, "z_um": 0.5}
            same = await asyncio.gather(*(http.post(url, json=body) for _ in range(20)))
            assert {r.status_code for r in same} == {200}
            assert len({r.text for r in same}) == 1
            # Twenty different values for the next acquisition: exactly one is recorded.
            nxt = (await http.get(f"/v1/slides/{slide_id}/next")).json()
            bodies = [
                {"row": nxt["row"], "col": nxt["col"], "sequence": 1, "z_um": 0.1 * i}
                for i in range(20)
            ]
            racing = await asyncio.gather(*(http.post(url, json=b) for b in bodies))
            assert sorted(r.status_code for r in racing) == [200] + [409] * 19
            slide = (await http.get(f"/v1/slides/{slide_id}")).json()
            assert slide["n_acquisitions"] == 2
        events = app.state.slides.store.events(slide_id)
        assert [e.sequence for e in events] == [0, 1]

    run(go())


STRATEGIES = ["kf-wiener0", "kf-wiener1-dir", "kf-gm1", "tile-skip", "survey-delaunay"]


def test_many_slides_scanned_concurrently_match_local_replays(app: FastAPI) -> None:
    slides = [(STRATEGIES[i % len(STRATEGIES)], 100 + i) for i in range(20)]

    async def go() -> list[FocusMap]:
        async with client(app) as http:
            ids = await asyncio.gather(*(create(http, name) for name, _ in slides))
            await asyncio.gather(
                *(scan(http, i, maps(seed)[1]) for i, (_, seed) in zip(ids, slides, strict=True))
            )
            return [await served_map(http, slide_id) for slide_id in ids]

    for served, (name, seed) in zip(run(go()), slides, strict=True):
        assert_same_maps(served, local_map(name, SETTINGS, seed))


def test_map_formats_agree(app: FastAPI) -> None:
    async def go() -> dict[str, httpx.Response]:
        async with client(app) as http:
            slide_id = await create(http)
            await scan(http, slide_id, maps(4)[1])
            url = f"/v1/slides/{slide_id}/map"
            return {
                f: await http.get(url, params={"format": f}) for f in ("json", "csv", "npy", "png")
            }

    replies = run(go())
    local = local_map("kf-wiener0", SETTINGS, 4)
    as_json = replies["json"].json()
    np.testing.assert_array_equal(np.array(as_json["posterior_um"]), local.posterior_um)
    np.testing.assert_allclose(np.array(as_json["smoothed_um"]), local.smoothed_um)
    assert (as_json["rows"], as_json["cols"]) == (ROWS, COLS)
    # Written without the model (for speed), yet exactly the model's JSON.
    assert api.FocusMapOut.model_validate_json(replies["json"].content).model_dump() == as_json

    assert replies["csv"].headers["content-type"].startswith("text/csv")
    table = np.genfromtxt(io.StringIO(replies["csv"].text), delimiter=",", names=True)
    assert table.shape == (ROWS * COLS,)
    np.testing.assert_array_equal(table["posterior_um"].reshape(ROWS, COLS), local.posterior_um)
    np.testing.assert_array_equal(table["stage_x_um"][:COLS], 1000.0 + 150.0 * np.arange(COLS))

    served = focus_map_of_npy(replies["npy"].content)
    assert_same_maps(served, local)
    assert np.load(io.BytesIO(replies["npy"].content)).dtype.names == MAP_LAYERS

    assert replies["png"].headers["content-type"] == "image/png"
    assert replies["png"].content.startswith(b"\x89PNG\r\n\x1a\n")


def test_diagnostics_summarise_the_innovations(app: FastAPI) -> None:
    async def go() -> dict[str, Any]:
        async with client(app) as http:
            slide_id = await create(http)
            await scan(http, slide_id, maps(5)[1])
            return (await http.get(f"/v1/slides/{slide_id}/diagnostics")).json()

    diagnostics = run(go())
    innovations = diagnostics["innovations"]
    assert diagnostics["n_accepted"] == innovations["n"] == ROWS * COLS
    assert diagnostics["n_acquisitions"] == diagnostics["n_accepted"] + diagnostics["n_rejected"]
    assert innovations["autocorrelation"][0] == pytest.approx(1.0)
    assert innovations["nis_low"] < 1.0 < innovations["nis_high"]
    assert 0.0 < innovations["mean_nis"] < 10.0
    assert diagnostics["innovations_note"] is None
    assert diagnostics["sigma_scale"] == 1.0  # measurements without a sigma: none to scale


def test_diagnostics_say_whether_the_stated_risk_is_met(app: FastAPI) -> None:
    """At the thesis noise (1.5 um, 1 um depth of field) one frame per tile cannot be sure
    enough for a 1% risk, and the diagnostics say so; keeping up to 5 frames of a tile
    (the default) cuts the risk tenfold, and the outcomes name the frames to keep."""
    truth, noisy = maps(6)

    async def go() -> list[tuple[dict[str, Any], FocusMap, list[dict[str, Any]]]]:
        results = []
        async with client(app) as http:
            for planes in (1, 5):
                body = slide_config("kf-2d-lean", SETTINGS)
                body["params"] = {"max_kept_planes": planes}
                response = await http.post("/v1/slides", json=body)
                slide_id = response.json()["id"]
                outcomes = []
                while not (next_ := (await http.get(f"/v1/slides/{slide_id}/next")).json())["done"]:
                    acquisition = to_domain.acquisition(api.Next.model_validate(next_))
                    assert acquisition is not None
                    measurement = simulated_measurement(
                        acquisition, noisy[acquisition.row, acquisition.col]
                    )
                    body = to_api.measurement_in(acquisition, measurement).model_dump(mode="json")
                    reply = await http.post(f"/v1/slides/{slide_id}/measurements", json=body)
                    outcomes.append({**reply.json(), "purpose": next_["purpose"]})
                diagnostics = (await http.get(f"/v1/slides/{slide_id}/diagnostics")).json()
                results.append((diagnostics["risk"], await served_map(http, slide_id), outcomes))
        return results

    (one_risk, one_map, one_outcomes), (five_risk, five_map, five_outcomes) = run(go())
    strategy = registry.create("kf-2d-lean", SETTINGS, {"max_kept_planes": 1})
    assert_same_maps(one_map, replay(strategy, truth, noisy).focus_map)
    assert one_risk["stated_risk"] == 0.01 and one_risk["n_tiles"] == ROWS * COLS
    assert one_map.out_of_focus_risk is not None
    assert one_risk["expected_out_of_focus"] == pytest.approx(np.mean(one_map.out_of_focus_risk))
    assert one_risk["expected_out_of_focus"] > 0.1
    assert "not met" in one_risk["note"]
    assert not any(outcome["planes_um"] for outcome in one_outcomes)

    # a tenth of the risk; what is left is the first row's, too unsure even for 5 frames
    assert five_risk["expected_out_of_focus"] < one_risk["expected_out_of_focus"] / 10
    assert five_map.out_of_focus_risk is not None
    over = five_map.out_of_focus_risk > 0.01
    assert over.sum() == five_risk["n_over_stated"] and over[1:].mean() < 0.5
    kept = [outcome for outcome in five_outcomes if outcome["planes_um"]]
    assert kept and all(3 <= len(outcome["planes_um"]) <= 5 for outcome in kept)
    planes_outcomes = [outcome for outcome in five_outcomes if outcome["purpose"] == "planes"]
    assert planes_outcomes  # image only: no second innovation of the same measurement
    assert not any(outcome["accepted"] or outcome["innovation_um"] for outcome in planes_outcomes)
    for outcome in kept:
        row, col = outcome["row"], outcome["col"]
        assert (
            min(outcome["planes_um"]) <= five_map.z_used_um[row, col] <= max(outcome["planes_um"])
        )


def test_bearer_token_when_configured(tmp_path: Path) -> None:
    async def go(app: FastAPI) -> None:
        async with client(app) as http:
            refused = await http.get("/v1/slides")
            assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
            wrong = await http.get("/v1/slides", headers={"Authorization": "Bearer nope"})
            assert wrong.status_code == 401
            assert wrong.json() == {
                "code": "unauthorized",
                "detail": "missing or wrong bearer token",
            }
            # the token before the body: a body that is no JSON was a 422 to anyone
            unread = await http.post(
                "/v1/slides", content=b"{", headers={"content-type": "application/json"}
            )
            assert unread.status_code == 401, unread.text
            assert (await http.get("/healthz")).status_code == 200
        async with client(app, token="s3cret") as http:
            assert (await http.get("/v1/slides")).status_code == 200

    with estimator(tmp_path / "estimator.sqlite", token="s3cret") as app:
        run(go(app))


def test_metrics_count_requests_measurements_and_rejections(app: FastAPI) -> None:
    async def go() -> str:
        async with client(app) as http:
            slide_id = await create(http)
            url = f"/v1/slides/{slide_id}/measurements"
            await http.post(url, json={"row": 0, "col": 0, "sequence": 0, "z_um": None,
                                       "flags": ["edge_high"]})  # fmt: skip
            await http.post(url, json={"row": 0, "col": 0, "sequence": 1, "z_um": 0.3})
            await http.post(url, json={"row": 0, "col": 0, "sequence": 1, "z_um": 0.3})  # again
            await http.get("/v1/slides/nope")
            return (await http.get("/metrics")).text

    text = run(go())
    lines = set(text.splitlines())
    assert "focustrack_estimator_measurements_total 2.0" in lines
    assert "focustrack_estimator_rejections_total 1.0" in lines
    assert "focustrack_estimator_slides 1.0" in lines
    assert (
        'focustrack_estimator_requests_total{method="POST",'
        'route="/v1/slides/{slide_id}/measurements",status="200"} 3.0'
    ) in lines
    assert (
        'focustrack_estimator_requests_total{method="GET",route="/v1/slides/{slide_id}",'
        'status="404"} 1.0'
    ) in lines
    assert any(
        line.startswith("focustrack_estimator_filter_duration_seconds_count") for line in lines
    )
