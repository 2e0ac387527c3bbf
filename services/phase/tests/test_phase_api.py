"""The phase REST API: the maths' answer as .npy or PNG, a 4xx naming the problem for every
kind of bad input, the command; one stack end to end through a real uvicorn server."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import tifffile
from fastapi.testclient import TestClient

from focustrack_core.serving import BackgroundServer
from focustrack_core.settings import SettingsError
from focustrack_phase import app as app_module
from focustrack_phase.acekf import AcekfOptions, FieldEstimate, reconstruct
from focustrack_phase.app import LEAST_LIMITS, PhaseLimits, create_app
from focustrack_phase.service import PhaseServiceSettings
from focustrack_phase.simulate import SyntheticStack, data_set_1

#: A small Data Set 1: 4 planes of 32x32 (a few ms to reconstruct).
PLANES, SIZE_PX = 4, 32


@pytest.fixture(scope="module")
def stack() -> SyntheticStack:
    return data_set_1(seed=3, planes=PLANES, size_px=SIZE_PX)


@pytest.fixture(scope="module")
def client() -> TestClient:
    limits = PhaseLimits(max_upload_bytes=200_000, max_frames=8, max_pixels=64 * 64)
    return TestClient(create_app(limits))


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def tiff_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, array, photometric="minisblack")
    return buffer.getvalue()


def tiff_pages(array: np.ndarray) -> bytes:
    """A TIFF written a page at a time (each page a series of its own, to tifffile)."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as tiff:
        for frame in array:
            tiff.write(frame.astype(np.uint16))
    return buffer.getvalue()


def opencv_tiff(array: np.ndarray) -> bytes:
    """A multi-page TIFF as OpenCV writes one: LZW-compressed."""
    ok, encoded = cv2.imencodemulti(".tiff", list(array.astype(np.uint16)))
    assert ok
    return encoded.tobytes()


def form(stack: SyntheticStack, **fields: object) -> dict[str, str]:
    """The form of a request for `stack` (its z, wavelength and pixel), `fields` added."""
    values: dict[str, object] = {
        "z_um": str(stack.z_um.tolist()),
        "wavelength_um": stack.wavelength_um,
        "pixel_um": stack.pixel_um,
    }
    return {name: str(value) for name, value in (values | fields).items()}


def post(
    client: TestClient | httpx.Client, data: bytes, fields: dict[str, str], query: str = ""
) -> httpx.Response:
    return client.post(f"/v1/phase/stack{query}", files={"stack": ("stack.bin", data)}, data=fields)


def read_npy(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    return np.load(io.BytesIO(response.content), allow_pickle=False)


def test_healthz(client: TestClient) -> None:
    response = client.get("/healthz")
    assert response.status_code == 200 and response.json() == {"status": "ok"}


@pytest.mark.parametrize("encode", [npy_bytes, tiff_bytes, tiff_pages, opencv_tiff])
def test_phase_and_amplitude_are_the_maths_own(
    client: TestClient, stack: SyntheticStack, encode
) -> None:
    answer = read_npy(post(client, encode(stack.stack_counts), form(stack), "?format=npy"))
    direct = reconstruct(stack.stack_counts, stack.z_um, stack.wavelength_um, stack.pixel_um)
    assert answer.dtype == np.float32 and answer.shape == (2, SIZE_PX, SIZE_PX)
    np.testing.assert_allclose(answer[0], direct.phase_rad, atol=1e-6)
    np.testing.assert_allclose(answer[1], direct.amplitude, rtol=1e-6)


def test_an_app_whose_ffts_run_on_two_threads_gives_the_same_answer(
    stack: SyntheticStack,
) -> None:
    threaded = TestClient(create_app(PhaseLimits(max_frames=8), fft_workers=2))
    answer = read_npy(post(threaded, npy_bytes(stack.stack_counts), form(stack), "?format=npy"))
    direct = reconstruct(stack.stack_counts, stack.z_um, stack.wavelength_um, stack.pixel_um)
    np.testing.assert_allclose(answer[0], direct.phase_rad, atol=1e-5)
    np.testing.assert_allclose(answer[1], direct.amplitude, rtol=1e-5)


def test_the_answer_says_how_much_of_the_image_is_glass(
    client: TestClient, stack: SyntheticStack
) -> None:
    anchored = post(client, npy_bytes(stack.stack_counts), form(stack))
    direct = reconstruct(stack.stack_counts, stack.z_um, stack.wavelength_um, stack.pixel_um)
    assert direct.background_share is not None
    share = float(anchored.headers["X-Background-Share"])
    assert share == pytest.approx(direct.background_share, abs=1e-4)
    own = post(client, npy_bytes(stack.stack_counts), form(stack, background="none"))
    assert own.status_code == 200 and "X-Background-Share" not in own.headers


def test_the_filter_settings_and_gain_reach_the_maths(
    client: TestClient, stack: SyntheticStack
) -> None:
    options = {
        "q0": 0.05,
        "p0": -0.01,
        "update": "paper",
        "condenser_na": 0.2,
        "amplitude_floor": 0.1,
        "prior_length_um": 2.0,
        "background": "none",
    }
    fields = form(stack, photons_per_count=2.0, **options)
    answer = read_npy(post(client, npy_bytes(stack.stack_counts), fields))  # npy: the default
    direct = reconstruct(
        stack.stack_counts,
        stack.z_um,
        stack.wavelength_um,
        stack.pixel_um,
        2.0,
        AcekfOptions(**options),
    )
    np.testing.assert_allclose(answer[0], direct.phase_rad, atol=1e-6)


def test_png_is_a_picture(client: TestClient, stack: SyntheticStack) -> None:
    response = post(client, npy_bytes(stack.stack_counts), form(stack), "?format=png")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    assert response.content.startswith(b"\x89PNG\r\n\x1a\n")


@pytest.mark.parametrize("shape", [(4000, 2), (2, 4000)])
def test_a_strip_of_a_frame_is_a_picture_of_bounded_size(shape: tuple[int, int]) -> None:
    """A frame's aspect once set the canvas' (here 200,000 pixels tall): now bounded."""
    png = app_module.phase_png(np.zeros(shape, dtype=np.float32))
    width, height = (int.from_bytes(png[offset : offset + 4], "big") for offset in (16, 20))
    assert max(width, height) < 2500
    assert max(width / height, height / width) < app_module.MAX_PICTURE_ASPECT + 0.5


def one_frame(stack: SyntheticStack) -> bytes:
    return npy_bytes(stack.stack_counts[:1])


def signed(stack: SyntheticStack) -> bytes:
    """Each frame less its mean: signed values about 0, the stack's mean a rounding error."""
    counts = stack.stack_counts.astype(np.float32)
    return npy_bytes(counts - counts.mean(axis=(1, 2), keepdims=True))


@pytest.mark.parametrize(
    ("data", "fields", "status", "needle"),
    [
        (lambda s: b"GIF89a" + bytes(64), {}, 415, "multi-page TIFF or a .npy"),
        (lambda s: npy_bytes(np.zeros((9, 8, 8))), {}, 413, "9 frames; the limit is 8"),
        (lambda s: npy_bytes(np.zeros((2, 65, 64))), {}, 413, "the limit is 4096"),
        (lambda s: bytes(200_001), {}, 413, "200000 bytes"),
        (None, {"z_um": "[1, 2, 3]"}, 422, "4 frames, got 3"),
        (None, {"z_um": "[1, 2, 3"}, 422, "z_um must be a JSON list"),
        (None, {"z_um": "[1, NaN, 2, 3]"}, 422, "z_um must be finite"),
        (None, {"wavelength_um": "-0.5"}, 422, "wavelength_um"),
        (None, {"pixel_um": "0"}, 422, "pixel_um"),
        (None, {"photons_per_count": "nan"}, 422, "photons_per_count"),
        (None, {"q0": "inf"}, 422, "q0"),
        (None, {"q0": "1000"}, 422, "q0"),  # a prior that flattens the phase
        (None, {"q0": "5e-324"}, 422, "q0"),  # a prior that holds the phase flat
        (None, {"photons_per_count": "1e-30"}, 422, "check photons_per_count"),
        (None, {"p0": "0.5"}, 422, "|p0| must be <= q0"),
        (None, {"amplitude_floor": "2"}, 422, "amplitude_floor"),
        (None, {"update": "sideways"}, 422, "phase_frame"),
        (None, {"condenser_na": "-0.1"}, 422, "condenser_na"),
        (None, {"prior_length_um": "-1"}, 422, "prior_length_um"),
        (None, {"background": "flat"}, 422, "'anchor' or 'none'"),
        (one_frame, {"z_um": "[1]"}, 422, "at least 2 frames; got 1"),
        (lambda s: npy_bytes(np.ones((4, 8))), {}, 422, "(frames, height, width)"),
        (lambda s: npy_bytes(np.full((4, 8, 8), np.nan)), {}, 422, "stack must be finite"),
        (lambda s: npy_bytes(np.ones((4, 8, 8), complex)), {}, 422, "real numbers"),
        (lambda s: npy_bytes(np.ones((4, 8, 8), "m8[s]")), {}, 422, "real numbers"),
        (lambda s: npy_bytes(np.ones(4096)), {}, 422, "frames of pixels"),
        (lambda s: tiff_pages(np.ones((9, 8, 8))), {}, 413, "more than 8 frames"),
        (lambda s: tiff_pages([np.ones((8, 8)), np.ones((8, 7))]), {}, 422, "one shape"),
        (None, {"z_um": "[true, false, true, false]"}, 422, "must list numbers"),
        (None, {"z_um": "[1e100, 1, 2, 3]"}, 422, "defocus phase of 8.36e+99 rad"),
        (None, {"pixel_um": "1e-300"}, 422, "are they all in um"),
        (None, {"z_um": "[0, 0, 0, 0]"}, 422, "under the 0.1 rad that shows any phase"),
        (None, {"pixel_um": "1000"}, 422, "under the 0.1 rad that shows any phase"),
        (signed, {}, 422, "not background-subtracted or signed frames"),
        (None, {"wavelength_um": "532"}, 422, "at most 20 um, got 532: is it in nm?"),
    ],
)
def test_bad_requests_say_what_is_wrong(
    client: TestClient, stack: SyntheticStack, data, fields, status: int, needle: str
) -> None:
    body = npy_bytes(stack.stack_counts) if data is None else data(stack)
    response = post(client, body, form(stack, **fields))
    assert response.status_code == status, response.text
    assert needle in response.text, response.text


def test_a_stack_sent_as_text_is_said_to_be_no_file(
    client: TestClient, stack: SyntheticStack
) -> None:
    """`-F stack=hello` (no @) was FastAPI's "Expected UploadFile, received: <class 'str'>"."""
    response = client.post("/v1/phase/stack", data=form(stack) | {"stack": "hello"})
    assert response.status_code == 422, response.text
    assert response.json() == {
        "detail": "form field stack must be a file (curl -F stack=@FILE), not text"
    }


def test_a_body_that_is_no_form_is_a_415(client: TestClient, stack: SyntheticStack) -> None:
    """JSON (the estimator's way) or a bare file was a 422 listing every field as missing."""
    response = client.post("/v1/phase/stack", json=form(stack))
    assert response.status_code == 415, response.text
    assert "the body is application/json; this route takes multipart/form-data" in response.text
    bare = client.post("/v1/phase/stack", content=npy_bytes(stack.stack_counts))
    assert bare.status_code == 415 and "of no media type" in bare.text, bare.text


def test_a_field_given_twice_is_refused(client: TestClient, stack: SyntheticStack) -> None:
    data = npy_bytes(stack.stack_counts)
    response = client.post(
        "/v1/phase/stack",
        files=[("stack", ("a.npy", data)), ("stack", ("b.npy", data))],
        data=form(stack),
    )
    assert response.status_code == 422 and "stack given more than once" in response.text
    fields: dict[str, Any] = form(stack) | {"wavelength_um": ["0.532", "0.633"]}
    response = client.post("/v1/phase/stack", files={"stack": ("a.npy", data)}, data=fields)
    assert response.status_code == 422 and "wavelength_um given more than once" in response.text


def test_a_misspelt_field_is_refused_not_left_at_its_default(
    client: TestClient, stack: SyntheticStack
) -> None:
    response = post(client, npy_bytes(stack.stack_counts), form(stack, photons_per_cont="4"))
    assert response.status_code == 422, response.text
    assert "unknown form field photons_per_cont" in response.text
    assert "photons_per_count" in response.text  # what the route takes


def test_bad_format_and_missing_field(client: TestClient, stack: SyntheticStack) -> None:
    response = post(client, npy_bytes(stack.stack_counts), form(stack), "?format=tiff")
    assert response.status_code == 422 and "format" in response.text
    # these answered a .npy: a misspelt format was left at its default, a second one won
    response = post(client, npy_bytes(stack.stack_counts), form(stack), "?fromat=png")
    assert response.status_code == 422, response.text
    assert "unknown query parameter; this route takes format" in response.text
    response = post(client, npy_bytes(stack.stack_counts), form(stack), "?format=png&format=npy")
    assert response.status_code == 422 and "given more than once" in response.text
    fields = form(stack)
    del fields["wavelength_um"]
    response = post(client, npy_bytes(stack.stack_counts), fields)
    assert response.status_code == 422 and "wavelength_um" in response.text


def test_a_token_is_required_when_set(stack: SyntheticStack) -> None:
    guarded = TestClient(create_app(token="secret"))
    body = npy_bytes(stack.stack_counts)
    assert post(guarded, body, form(stack)).status_code == 401
    guarded.headers["Authorization"] = "Bearer secret"
    assert post(guarded, body, form(stack)).status_code == 200


def test_without_the_token_the_body_is_not_read(stack: SyntheticStack) -> None:
    """The token is checked before the form is parsed: a broken form was a 422 of the
    parser's words to a client without the token, whose whole upload the service read."""
    guarded = TestClient(create_app(token="secret"))
    broken = {"content-type": "multipart/form-data; boundary=x"}
    refused = guarded.post("/v1/phase/stack", content=b"--x\r\nnot a part", headers=broken)
    assert refused.status_code == 401, refused.text
    assert refused.json() == {"detail": "missing or wrong bearer token"}
    assert refused.headers["www-authenticate"] == "Bearer"
    guarded.headers["Authorization"] = "Bearer secret"
    assert (
        guarded.post("/v1/phase/stack", content=b"--x\r\nnot a part", headers=broken).status_code
        == 422
    )


@pytest.mark.parametrize("token", [None, "secret"])
def test_the_openapi_document_asks_for_a_token_only_when_one_is_set(token: str | None) -> None:
    document = create_app(token=token).openapi()
    schemes = document.get("components", {}).get("securitySchemes", {})
    assert ("security" in document["paths"]["/v1/phase/stack"]["post"]) == (token is not None)
    assert bool(schemes) == (token is not None)


def test_end_to_end_on_uvicorn_healthz_answers_and_a_stack_more_is_a_503_while_one_is_held(
    stack: SyntheticStack, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A TIFF through a real server on a free loopback port gets the maths' answer; while
    its reconstruction is held on its worker thread, /healthz answers and a second stack,
    beyond max_concurrent, is a 503 at once (six stacks at once had taken 4.5 GB)."""
    under_way, release = threading.Event(), threading.Event()

    def held_reconstruct(*args: Any) -> FieldEstimate:
        under_way.set()
        release.wait(30.0)
        return reconstruct(*args)

    monkeypatch.setattr(app_module, "reconstruct", held_reconstruct)
    responses: list[httpx.Response] = []
    body = tiff_bytes(stack.stack_counts)
    with (
        BackgroundServer(create_app(PhaseLimits(max_concurrent=1))) as server,
        httpx.Client(base_url=server.url, timeout=30.0) as http,
    ):
        worker = threading.Thread(target=lambda: responses.append(post(http, body, form(stack))))
        worker.start()
        assert under_way.wait(30.0)
        health = httpx.get(server.url + "healthz", timeout=5.0)
        with httpx.Client(base_url=server.url, timeout=5.0) as other:
            busy = post(other, body, form(stack))
        release.set()
        worker.join(30.0)
        metrics = http.get("metrics").text.splitlines()
        assert post(http, body, form(stack)).status_code == 200  # the place is free again
    assert health.status_code == 200 and health.json() == {"status": "ok"}
    assert busy.status_code == 503 and busy.headers["retry-after"] == "1", busy.text
    assert "the most requests it takes at once (1)" in busy.json()["detail"]
    counted = 'focustrack_phase_requests_total{method="POST",route="/v1/phase/stack",status="503"}'
    assert f"{counted} 1.0" in metrics
    answer = read_npy(responses[0])
    direct = reconstruct(stack.stack_counts, stack.z_um, stack.wavelength_um, stack.pixel_um)
    np.testing.assert_allclose(answer[0], direct.phase_rad, atol=1e-6)


def run_command(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "focustrack", "serve", "phase", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_the_command_helps_and_refuses_a_bad_option() -> None:
    helped = run_command("--help")
    assert helped.returncode == 0, helped.stderr
    for option in ("--port", "--max-frames", "--max-pixels", "--max-concurrent", "--settings"):
        assert option in helped.stdout
    assert "FOCUSTRACK_PHASE_PORT" in helped.stdout
    refused = run_command("--port", "70000")
    assert refused.returncode == 2 and "--port" in refused.stderr, refused.stderr
    opened = run_command("--host", "0.0.0.0")
    assert opened.returncode == 2 and "without a token" in opened.stderr, opened.stderr


def test_settings_from_a_file_and_the_environment_and_heavy_modules_left_for_later(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("FOCUSTRACK_PHASE_MAX_FRAMES", "21")
    monkeypatch.setenv("FOCUSTRACK_PHASE_MAX_PIXELS", "4096")
    file = tmp_path / "phase.toml"
    file.write_text("max_frames = 5\nport = 8301\n")
    settings = PhaseServiceSettings.load(file)
    assert settings.port == 8301  # from the file; the environment over it for the frames
    assert settings.limits() == PhaseLimits(max_frames=21, max_pixels=4096)
    with pytest.raises(SettingsError, match=r"--max-frames .*greater than or equal to 2"):
        PhaseServiceSettings.load(max_frames=1)  # every stack needs two: it would admit none
    with pytest.raises(ValueError, match="max_pixels must be at least 4, got 1"):
        PhaseLimits(max_pixels=1)
    assert PhaseServiceSettings.load(max_concurrent=3).limits().max_concurrent == 3
    with pytest.raises(SettingsError, match=r"--max-concurrent .*greater than or equal to 1"):
        PhaseServiceSettings.load(max_concurrent=0)  # no stack would ever be taken
    assert settings.fft_workers == 1
    cores = os.cpu_count() or 1
    assert PhaseServiceSettings.load(fft_workers=cores).fft_workers == cores
    with pytest.raises(SettingsError, match=r"--fft-workers .*less than or equal to"):
        PhaseServiceSettings.load(fft_workers=cores + 1)  # threads beyond the cores: no gain
    with pytest.raises(SettingsError, match=r"--wavelength-um .*less than or equal to 20"):
        PhaseServiceSettings.load(wavelength_um=532)  # nm, not um
    with pytest.raises(ValueError, match="--fft-workers"):
        PhaseServiceSettings.load(fft_workers=0)
    # matplotlib (the PNG) and tifffile (TIFF uploads) wait for the first request needing them
    loaded = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, focustrack_phase.service; "
            "print(sorted({'matplotlib', 'tifffile'} & set(sys.modules)))",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert loaded.stdout.strip() == "[]"


def test_metrics_count_each_route_and_status() -> None:
    client = TestClient(create_app())  # a registry of its own: counts start at zero
    assert client.post("/v1/phase/stack", data={"z_um": "[0]"}).status_code == 422
    lines = client.get("/metrics").text.splitlines()
    expected = (
        'focustrack_phase_requests_total{method="POST",route="/v1/phase/stack",status="422"} 1.0'
    )
    assert expected in lines


def test_refusals_before_routing_count_against_their_route() -> None:
    """A 401 (no token) and a 413 (a declared length over the limit) are answered by the
    middleware before the router runs: they were counted as route "unmatched"."""
    limits = PhaseLimits(max_upload_bytes=LEAST_LIMITS["max_upload_bytes"])
    client = TestClient(create_app(limits, token="secret"))
    assert client.post("/v1/phase/stack", content=b"x").status_code == 401
    client.headers["Authorization"] = "Bearer secret"
    assert client.post("/v1/phase/stack", content=b"x" * 5000).status_code == 413
    assert client.get("/v1/nothing/here").status_code == 404
    lines = client.get("/metrics").text.splitlines()
    for status in (401, 413):
        line = f'requests_total{{method="POST",route="/v1/phase/stack",status="{status}"}} 1.0'
        assert f"focustrack_phase_{line}" in lines, line
    assert (
        'focustrack_phase_requests_total{method="GET",route="unmatched",status="404"} 1.0' in lines
    )


def test_a_form_field_over_the_parsers_part_limit_is_a_413(stack: SyntheticStack) -> None:
    """A million heights in z_um were a 400 "Part exceeded maximum size of 1024KB.", a
    status the API does not document."""
    client = TestClient(create_app(PhaseLimits(max_frames=8)))  # a body of 256 MB at most
    fields = form(stack) | {"z_um": json.dumps(list(range(300_000)))}
    response = post(client, npy_bytes(stack.stack_counts), fields)
    assert response.status_code == 413, response.text
    assert "the form cannot be read: Part exceeded maximum size" in response.json()["detail"]
