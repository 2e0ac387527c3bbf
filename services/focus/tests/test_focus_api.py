"""The focus REST API: results, and a 4xx naming the problem for every kind of bad input."""

from __future__ import annotations

import io
import re
from collections.abc import Callable, Iterator

import httpx
import numpy as np
import pytest
import tifffile
from fastapi import FastAPI
from fastapi.testclient import TestClient

from focustrack_focus.app import FocusLimits, create_app

Z_UM = np.arange(-3.0, 3.01, 0.5)
TRUTH_UM = 0.3


@pytest.fixture(scope="module")
def client() -> TestClient:
    return TestClient(create_app(limits=FocusLimits(max_upload_bytes=4_000_000)))


@pytest.fixture(scope="module")
def frames(render: Callable[..., np.ndarray]) -> np.ndarray:
    """A stack of a field of cells: (13, 96, 96) uint16."""
    return render(96, Z_UM, TRUTH_UM, 5)


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def tiff_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, array)
    return buffer.getvalue()


def post_stack(client, data: bytes, z: str, **form: str) -> httpx.Response:
    return client.post(
        "/v1/focus/stack", files={"stack": ("stack.bin", data)}, data={"z_um": z, **form}
    )


def z_text(z: np.ndarray = Z_UM) -> str:
    return ",".join(f"{value:g}" for value in z)


def test_healthz(client: TestClient) -> None:
    response = client.get("/healthz")
    assert response.status_code == 200 and response.json()["status"] == "ok"


@pytest.mark.parametrize("encode", [npy_bytes, tiff_bytes])
def test_stack_as_npy_or_tiff(client: TestClient, frames: np.ndarray, encode) -> None:
    response = post_stack(client, encode(frames), z_text())
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["best_z_um"] == pytest.approx(TRUTH_UM, abs=0.15)
    assert 0 < body["sigma_um"] < 0.5 and body["flags"] == []
    assert body["metric"] == "normalised_variance" and len(body["scores"]) == Z_UM.size


def test_one_frame_is_a_look(client: TestClient, frames: np.ndarray) -> None:
    """A (1, H, W) stack is answered, with no focus (one frame has no curve): cells in view."""
    look = post_stack(client, npy_bytes(frames[:1]), z_text(Z_UM[:1]))
    assert look.status_code == 200, look.text
    assert look.json()["best_z_um"] is None and look.json()["flags"] == []
    assert look.json()["z_um"] == [Z_UM[0]] and len(look.json()["scores"]) == 1


def test_a_stack_or_its_heights_given_twice_is_refused(
    client: TestClient, frames: np.ndarray
) -> None:
    """Which of two stacks, or of two lists of heights, was meant is not for us to guess."""
    data = npy_bytes(frames)
    twice = client.post(
        "/v1/focus/stack",
        files=[("stack", ("a.npy", data)), ("stack", ("b.npy", data))],
        data={"z_um": z_text()},
    )
    assert twice.status_code == 422 and "stack given more than once" in twice.text
    twice = client.post(
        "/v1/focus/stack", files={"stack": ("a.npy", data)}, data={"z_um": [z_text(), z_text()]}
    )
    assert twice.status_code == 422 and "z_um given more than once" in twice.text


def test_a_misspelt_field_is_refused_not_left_at_its_default(
    client: TestClient, frames: np.ndarray
) -> None:
    response = post_stack(client, npy_bytes(frames), z_text(), Mode="valley")
    assert response.status_code == 422 and "unknown form field Mode" in response.text


def test_stack_options_and_json_z(client: TestClient, frames: np.ndarray) -> None:
    rgb = np.stack([frames // 2, frames, frames // 3], axis=-1)
    response = post_stack(
        client, npy_bytes(rgb), str(Z_UM.tolist()), metric="tenengrad", channel="1"
    )
    assert response.status_code == 200, response.text
    assert response.json()["metric"] == "tenengrad"
    assert response.json()["best_z_um"] == pytest.approx(TRUTH_UM, abs=0.15)


def test_curve(client: TestClient) -> None:
    scores = (1 + 4 * np.exp(-0.5 * ((Z_UM - 0.7) / 0.8) ** 2)).tolist()
    response = client.post("/v1/focus/curve", json={"z_um": Z_UM.tolist(), "scores": scores})
    assert response.status_code == 200, response.text
    assert response.json()["best_z_um"] == pytest.approx(0.7, abs=0.05)
    edge = client.post("/v1/focus/curve", json={"z_um": [0, 1, 2], "scores": [1, 2, 3]})
    assert edge.status_code == 200 and edge.json()["flags"] == ["edge_high"]
    assert response.json()["chosen_probability"] == 1.0
    assert response.json()["runner_up_z_um"] is None and response.json()["posterior_z_um"] is None


def test_curve_with_a_prior_picks_its_peak_and_returns_the_posterior(client: TestClient) -> None:
    z = np.arange(-5.0, 5.01, 0.5)
    two_peaks = (
        1 + 4 * np.exp(-0.5 * ((z + 2) / 0.8) ** 2) + 3.8 * np.exp(-0.5 * ((z - 2.5) / 0.8) ** 2)
    )
    body = {"z_um": z.tolist(), "scores": two_peaks.tolist()}
    blind = client.post("/v1/focus/curve", json=body).json()
    assert blind["best_z_um"] == pytest.approx(-2.0, abs=0.1)
    assert blind["runner_up_z_um"] == 2.5 and "ambiguous" in blind["flags"]
    informed = client.post("/v1/focus/curve", json=body | {"prior": {"z_um": 2.0, "sigma_um": 1.0}})
    result = informed.json()
    assert informed.status_code == 200, informed.text
    # best_z_um is the curve's own measurement; the posterior adds the prior to it
    assert result["best_z_um"] == pytest.approx(2.5, abs=0.1) and result["runner_up_z_um"] == -2.0
    assert result["best_z_um"] > result["posterior_z_um"] > 2.0
    assert result["posterior_sigma_um"] < min(result["sigma_um"], 1.0)


@pytest.mark.parametrize(
    ("body", "status", "needle"),
    [
        ({"z_um": [0, 1, 2, 3], "scores": [1, 2, 1]}, 422, "4 z values but 3 scores"),
        ({"z_um": [0, 1], "scores": [1, 2]}, 422, "at least 3"),
        ({"z_um": [0, 1, 1], "scores": [1, 2, 1]}, 422, "distinct"),
        ({"z_um": [0, 1, 2], "scores": [1, 2, 1], "mode": "sideways"}, 422, "mode"),
        ({"z_um": [0, 1, 2], "scores": [1, 2, 1], "prior": {"z_um": 1}}, 422, "sigma_um"),
        # a label is echoed back: 100 000 characters were, whole
        ({"z_um": [0, 1, 2], "scores": [1, 2, 1], "metric": "M" * 100_000}, 422, "at most 64"),
        # an empty label picked no profile entry, unseen
        ({"z_um": [0, 1, 2], "scores": [1, 2, 1], "metric": ""}, 422, "at least 1 character"),
    ],
)
def test_bad_curves(client: TestClient, body: dict, status: int, needle: str) -> None:
    response = client.post("/v1/focus/curve", json=body)
    assert response.status_code == status and needle in response.text, response.text
    assert len(response.text) < 1000  # what is wrong, not the input


@pytest.mark.parametrize(
    ("z", "needle"),
    [
        # was "z_um must be a JSON list or comma-separated numbers: Expecting value: line 1 ..."
        ("0,1,2,inf", "z_um must be finite numbers (um), a JSON list or comma-separated: 'inf'"),
        ("[0, 1, 2, -inf]", "'-inf' is not one"),
        ("0,1,,2", "'' is not one"),
        ("0, 1, 2 um", "'2 um' is not one"),
        ("[[0, 1], [2, 3]]", "z_um must be a flat list of numbers"),  # parse_z_list's own
    ],
)
def test_z_that_are_no_finite_numbers_are_named(
    client: TestClient, frames: np.ndarray, z: str, needle: str
) -> None:
    response = post_stack(client, npy_bytes(frames[:4]), z)
    assert response.status_code == 422 and needle in response.json()["detail"], response.text


@pytest.mark.parametrize(
    ("prior", "field", "needle"),
    [
        ({"z_um": 2, "sigma_um": 0}, "sigma_um", "greater than or equal to 0.000001"),
        ({"z_um": 2, "sigma_um": 1e-200}, "sigma_um", "greater than or equal to 0.000001"),
        ({"z_um": 2, "sigma_um": 1e200}, "sigma_um", "less than or equal to 1000000"),
        ({"z_um": 1e300, "sigma_um": 1}, "z_um", "less than or equal to 1000000"),
        ({"z_um": -1e300, "sigma_um": 1}, "z_um", "greater than or equal to -1000000"),
    ],
)
def test_a_prior_out_of_bounds_is_a_422_naming_its_field(
    client: TestClient, prior: dict, field: str, needle: str
) -> None:
    """A prior the maths cannot compute (1 / sigma**2 overflowing) was a 500."""
    response = client.post(
        "/v1/focus/curve", json={"z_um": [1, 2, 3], "scores": [1, 2, 1], "prior": prior}
    )
    assert response.status_code == 422, response.text
    [error] = response.json()["detail"]
    assert error["loc"] == ["body", "prior", field] and needle in error["msg"], error


#: The numbers of a curve's reply that say where its focus is.
READING = ("best_z_um", "sigma_um", "runner_up_z_um", "chosen_probability")


def test_a_curve_reads_the_same_at_any_scale_of_its_scores(client: TestClient) -> None:
    """Scores of 1e-160 underflowed in the fit: a wrong 200 (best 1.5, sigma 0.5), or a
    422 "Singular matrix" for [1e-200, 2e-200, 1e-200]."""
    z = np.arange(-5.0, 5.01, 0.5)
    rng = np.random.default_rng(4)
    clean = np.exp(-0.5 * ((z - 1.3) / 1.0) ** 2)
    noisy_two_peaks = 1 + 4 * clean + 3 * np.exp(-0.5 * ((z + 3) / 0.8) ** 2)
    noisy_two_peaks += 0.05 * rng.standard_normal(z.size)
    for scores in (clean, noisy_two_peaks):
        replies = [
            client.post("/v1/focus/curve", json={"z_um": z.tolist(), "scores": s}).json()
            for s in (scores.tolist(), (scores * 1e-160).tolist(), (scores * 1e100).tolist())
        ]
        first = replies[0]
        assert first["best_z_um"] == pytest.approx(1.3, abs=0.05) and first["sigma_um"] < 0.2
        for scaled in replies[1:]:
            assert scaled["flags"] == first["flags"]
            for key in READING:
                expected = first[key]
                assert scaled[key] == (expected and pytest.approx(expected, rel=1e-9)), key
    tiny = client.post(
        "/v1/focus/curve", json={"z_um": [1, 2, 3], "scores": [1e-200, 2e-200, 1e-200]}
    )
    assert tiny.status_code == 200 and tiny.json()["best_z_um"] == 2.0, tiny.text


def test_z_steps_below_a_picometre_are_refused(client: TestClient) -> None:
    body = {"z_um": [1e-300, 2e-300, 3e-300], "scores": [1, 2, 1]}
    response = client.post("/v1/focus/curve", json=body)
    assert response.status_code == 422
    assert "at least 1e-06 um apart: 1e-300 and 2e-300 um" in response.json()["detail"]
    body["z_um"] = [0.0, 1e-6, 2e-6]  # a picometre is fine
    assert client.post("/v1/focus/curve", json=body).json()["best_z_um"] == 1e-6


def test_a_one_frame_spike_on_a_zero_baseline_is_flat(client: TestClient) -> None:
    """Through the curve and through a stack of black frames with one hot pixel in one:
    both were read as `edge_low` at the first frame."""
    z = np.arange(-5.0, 5.01, 0.5)
    spike = [0.0] * 10 + [1.0] + [0.0] * 10
    curve = client.post("/v1/focus/curve", json={"z_um": z.tolist(), "scores": spike})
    assert curve.status_code == 200 and curve.json()["flags"] == ["flat"], curve.text
    black = np.zeros((z.size, 64, 64), np.uint16)
    black[10, 20, 30] = 4000
    stack = post_stack(client, npy_bytes(black), z_text(z))
    assert stack.status_code == 200, stack.text
    assert stack.json()["best_z_um"] is None and "flat" in stack.json()["flags"]
    assert "edge_low" not in stack.json()["flags"]


def test_a_background_subtracted_stack_is_refused_not_read(
    client: TestClient, frames: np.ndarray
) -> None:
    """The metrics divide by each frame's mean: minus the stack's mean, a clean stack gave
    a confident, wrong focus with no flag."""
    signed = frames.astype(np.float32) - np.float32(frames.mean())
    response = post_stack(client, npy_bytes(signed), z_text())
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert re.fullmatch(
        r"frame \d+ has a mean intensity of -[\d.e+-]+: the focus metrics take intensities "
        r"\(raw counts\), not background-subtracted or signed frames",
        detail,
    ), detail
    lifted = post_stack(client, npy_bytes(signed - signed.min()), z_text())  # offset, >= 0
    assert lifted.json()["best_z_um"] == pytest.approx(TRUTH_UM, abs=0.15), lifted.text


def post_json(client: TestClient, text: str | bytes) -> httpx.Response:
    """POST `text` as it is (a body json= could not write: a key twice, NaN)."""
    return client.post(
        "/v1/focus/curve", content=text, headers={"content-type": "application/json"}
    )


@pytest.mark.parametrize(
    ("body", "loc"),
    [
        ({"z_um": ["1", "2", "3"], "scores": [1, 2, 1]}, ["body", "z_um", 0]),
        ({"z_um": [1, 2, 3], "scores": [True, False, True]}, ["body", "scores", 0]),
        (
            {"z_um": [1, 2, 3], "scores": [1, 2, 1], "prior": {"z_um": "2", "sigma_um": 1}},
            ["body", "prior", "z_um"],
        ),
        (
            {"z_um": [1, 2, 3], "scores": [1, 2, 1], "prior": {"z_um": 2, "sigma_um": True}},
            ["body", "prior", "sigma_um"],
        ),
    ],
)
def test_strings_and_booleans_are_not_numbers(client: TestClient, body: dict, loc: list) -> None:
    response = client.post("/v1/focus/curve", json=body)
    assert response.status_code == 422, response.text
    assert {"loc": loc, "msg": "Input should be a valid number"} in [
        {"loc": error["loc"], "msg": error["msg"]} for error in response.json()["detail"]
    ]


def test_integers_are_numbers(client: TestClient) -> None:
    body = {"z_um": [1, 2, 3], "scores": [1, 2, 1], "prior": {"z_um": 2, "sigma_um": 1}}
    response = client.post("/v1/focus/curve", json=body)
    assert response.status_code == 200 and response.json()["best_z_um"] == 2.0, response.text


@pytest.mark.parametrize(
    ("text", "detail"),
    [
        (
            '{"z_um": [1, 2, 3], "scores": [1, 2, 1], "scores": [3, 2, 1]}',
            "JSON key 'scores' given more than once; send each key once",
        ),
        (
            '{"z_um": [1, 2, 3], "scores": [1, 2, 1], "prior": {"z_um": 1, "sigma_um": 1, '
            '"z_um": 3}}',
            "JSON key 'z_um' given more than once; send each key once",
        ),
        ('{"z_um": [1, 2, 3], "scores": [1, 2, 1]', "the body is not JSON: Expecting"),
        (b'{"metric": "\xff"}', "the body is not JSON"),  # not UTF-8
    ],
)
def test_a_key_given_twice_or_a_body_not_json_is_refused(
    client: TestClient, text: str | bytes, detail: str
) -> None:
    """json keeps the last of two keys, silently: which was meant is not for us to guess."""
    response = post_json(client, text)
    assert response.status_code == 422 and response.json()["detail"].startswith(detail), (
        response.text
    )


def test_non_finite_curve_is_refused(client: TestClient) -> None:
    response = post_json(client, '{"z_um": [0, 1, 2], "scores": [1, NaN, 1]}')
    assert response.status_code == 422 and "finite" in response.text, response.text


def test_bad_stacks(client: TestClient, frames: np.ndarray) -> None:
    def check(data: bytes, z: str, status: int, needle: str, **form: str) -> None:
        response = post_stack(client, data, z, **form)
        assert response.status_code == status, response.text
        assert needle in response.json()["detail"], response.text

    check(npy_bytes(frames), z_text(Z_UM[:-1]), 422, "13 frames but 12 z values")
    check(
        npy_bytes(frames[0]),
        z_text(Z_UM[:1]),
        422,
        "the .npy is a single (96, 96) frame: a stack is frames first, (n, H, W) or "
        "(n, H, W, C); send one frame (a look) as (1, H, W)",
    )
    rgb_frame = np.stack([frames[0]] * 3, axis=-1)  # (H, W, 3): 96 frames of 3 pixels?
    check(
        npy_bytes(rgb_frame),
        z_text(Z_UM[:1]),
        422,
        "96 frames but 1 z values: one z per frame needed (a stack is frames first, "
        "(n, H, W) or (n, H, W, C); got shape (96, 96, 3))",
    )
    check(npy_bytes(frames[:2]), z_text(Z_UM[:2]), 422, "at least 3")
    nan = frames.astype(np.float32)
    nan[3, 5, 5] = np.nan
    check(npy_bytes(nan), z_text(), 422, "finite")
    check(npy_bytes(frames), "0,1,x", 422, "z_um must be")
    check(npy_bytes(frames), z_text(), 422, "unknown focus metric", metric="nope")
    for not_finite in ("nan", "inf"):  # nan was "Input should be less than or equal to 64"
        response = post_stack(client, npy_bytes(frames), z_text(), lowpass_sigma_px=not_finite)
        [error] = response.json()["detail"]
        assert error["loc"] == ["body", "lowpass_sigma_px"], response.text
        assert error["msg"] == "Input should be a finite number", response.text
    check(b"GIF89a not a stack", z_text(), 415, "TIFF or a .npy")
    as_json = client.post("/v1/focus/stack", json={"z_um": z_text()})  # was a 422: 2 missing
    assert as_json.status_code == 415 and "takes multipart/form-data" in as_json.text
    check(b"\x93NUMPY broken", z_text(), 422, ".npy file cannot be read")
    big = np.zeros((20, 400, 400), np.uint16)  # 6.4 MB > the 4 MB limit of this app
    check(npy_bytes(big), z_text(np.arange(20.0)), 413, "exceeds")


def test_real_uvicorn_server(
    http: httpx.Client, frames: np.ndarray, serve: Callable[[FastAPI], str]
) -> None:
    base = serve(create_app())
    assert http.get(f"{base}/healthz").json()["status"] == "ok"
    response = http.post(
        f"{base}/v1/focus/stack",
        files={"stack": ("stack.tif", tiff_bytes(frames))},
        data={"z_um": z_text()},
        timeout=30,
    )
    assert response.status_code == 200, response.text
    assert response.json()["best_z_um"] == pytest.approx(TRUTH_UM, abs=0.15)
    assert "/v1/focus/stack" in http.get(f"{base}/openapi.json").json()["paths"]


def _refs(node: object) -> Iterator[str]:
    """Every "$ref" in a JSON document."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref":
                yield value
            else:
                yield from _refs(value)
    elif isinstance(node, list):
        for item in node:
            yield from _refs(item)


def test_every_reference_of_the_openapi_document_resolves() -> None:
    """The curve's request schema referred to "#/$defs/PeakMode" from the document's root."""
    document = TestClient(create_app(token="secret")).get("/openapi.json").json()
    refs = set(_refs(document))
    assert "#/components/schemas/PriorModel" in refs and "#/components/schemas/PeakMode" in refs
    for ref in refs:
        assert ref.startswith("#/"), ref
        node = document
        for part in ref[2:].split("/"):
            assert part in node, f"{ref} does not resolve"
            node = node[part]
    body = document["paths"]["/v1/focus/curve"]["post"]["requestBody"]
    assert body["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/CurveRequest"
    }
    curve = document["components"]["schemas"]["CurveRequest"]
    assert curve["required"] == ["z_um", "scores"] and "prior" in curve["properties"]


def test_the_openapi_document_says_what_each_route_refuses() -> None:
    open_app = TestClient(create_app()).get("/openapi.json").json()["paths"]
    with_token = TestClient(create_app(token="secret")).get("/openapi.json").json()["paths"]
    for paths, token in ((open_app, []), (with_token, ["401"])):
        curve = paths["/v1/focus/curve"]["post"]["responses"]
        stack = paths["/v1/focus/stack"]["post"]["responses"]
        assert sorted(curve) == ["200", *token, "408", "413", "422"]
        assert sorted(stack) == ["200", *token, "408", "413", "415", "422", "503"]
        for refusal in (*token, "408", "413", "422"):
            for responses in (curve, stack):
                schema = responses[refusal]["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/ErrorReply"}
    assert "1048576 bytes" in open_app["/v1/focus/curve"]["post"]["responses"]["413"]["description"]


def test_metrics_count_and_time_each_route_and_status() -> None:
    """Prometheus text at /metrics: requests by route template and status, with latencies."""
    client = TestClient(create_app())  # a registry of its own: counts start at zero
    curve = {"z_um": [-2.0, -1.0, 0.0, 1.0, 2.0], "scores": [1.0, 3.0, 5.0, 3.0, 1.0]}
    assert client.post("/v1/focus/curve", json=curve).status_code == 200
    assert client.post("/v1/focus/curve", json={"z_um": [0.0]}).status_code == 422
    lines = client.get("/metrics").text.splitlines()
    route = 'route="/v1/focus/curve"'
    for status in ("200", "422"):
        assert (
            f'focustrack_focus_requests_total{{method="POST",{route},status="{status}"}} 1.0'
            in lines
        )
    assert f"focustrack_focus_request_duration_seconds_count{{{route}}} 2.0" in lines


def test_a_query_parameter_the_route_does_not_take_is_refused(client: TestClient) -> None:
    """`?metric=tenengrad` is no way to pick a metric (a form field is): it was ignored."""
    body = {"z_um": [0, 1, 2], "scores": [1, 2, 1]}
    response = client.post("/v1/focus/curve?metric=tenengrad", json=body)
    assert response.status_code == 422, response.text
    assert "unknown query parameter; this route takes none" in response.text
    assert client.post("/v1/focus/curve", json=body).status_code == 200
