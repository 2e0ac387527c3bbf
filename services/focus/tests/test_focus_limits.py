"""The focus REST API's limits: every hostile input is a 4xx that says why, on a
real uvicorn server on loopback. Each exploit found when the API was attacked is one check
here."""

from __future__ import annotations

import io
import socket
import time
from collections.abc import Callable
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
import tifffile
from fastapi import FastAPI

from focustrack_core.testing import within
from focustrack_focus.app import FocusLimits, create_app, json_depth_exceeds
from focustrack_focus.bombs import BOMB_FRAMES, BOMB_SIDE, npy_with_shape, zlib_tiff_bomb

Serve = Callable[[FastAPI], str]


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _post_stack(
    http: httpx.Client, url: str, data: bytes, n_frames: int, **form: str
) -> httpx.Response:
    fields = {"z_um": ",".join(str(float(z)) for z in range(n_frames)), **form}
    return http.post(
        f"{url}/v1/focus/stack", files={"stack": ("stack", data)}, data=fields, timeout=60
    )


def _refused(response: httpx.Response, status: int, needle: str) -> None:
    assert response.status_code == status, response.text
    assert needle in str(response.json()["detail"]), response.text


def test_the_zlib_tiff_bomb_is_refused_from_its_header(http: httpx.Client, serve: Serve) -> None:
    bomb = zlib_tiff_bomb()
    with tifffile.TiffFile(io.BytesIO(bomb)) as tiff:  # the bomb is real: 3.6 GB of pixels
        assert len(tiff.pages) == BOMB_FRAMES and tiff.pages[0].shape == (BOMB_SIDE, BOMB_SIDE)
    assert len(bomb) < 4_000_000 < 3_600_000_000 < BOMB_FRAMES * BOMB_SIDE**2 * 2
    url = serve(create_app())
    _refused(_post_stack(http, url, bomb, BOMB_FRAMES), 413, "would decode to 3623878656 bytes")


def test_npy_headers_with_huge_shapes_are_refused_before_any_allocation(
    http: httpx.Client, serve: Serve
) -> None:
    url = serve(create_app())
    _refused(_post_stack(http, url, npy_with_shape((10**6, 10**6, 10**6)), 5), 413, "frames")
    _refused(_post_stack(http, url, npy_with_shape((5, 10**6, 10**6)), 5), 413, "would decode to")
    long_header = npy_with_shape(tuple([1] * 5000))  # a header over numpy's 10 000 bytes
    _refused(_post_stack(http, url, long_header, 5), 422, ".npy file cannot be read")


def test_too_many_frames_and_bytes_are_413(http: httpx.Client, serve: Serve) -> None:
    limits = FocusLimits(max_upload_bytes=100_000, max_frames=10, max_decoded_bytes=50_000)
    url = serve(create_app(limits=limits))
    frames = np.zeros((11, 4, 4), np.uint16)
    _refused(_post_stack(http, url, _npy(frames), 11), 413, "11 frames; the limit is 10")
    _refused(_post_stack(http, url, _npy(np.zeros((5, 80, 80), np.uint16)), 5), 413, "decode to")
    big = _post_stack(http, url, _npy(np.zeros((5, 200, 200), np.uint16)), 5)
    _refused(big, 413, "exceeds the limit of 100000 bytes")


def test_zero_size_frames_and_a_low_pass_larger_than_the_frame_are_422(
    http: httpx.Client, serve: Serve
) -> None:
    url = serve(create_app())
    _refused(_post_stack(http, url, _npy(np.zeros((5, 0, 8), np.uint16)), 5), 422, "no pixels")
    _refused(_post_stack(http, url, _npy(np.zeros((5, 8, 0, 3), np.uint16)), 5), 422, "no pixels")
    noisy = np.random.default_rng(0).integers(0, 4000, (5, 64, 64)).astype(np.uint16)
    for sigma_px in ("64", "20"):  # each once answered 500 (ZeroDivisionError, cv2 assertion)
        response = _post_stack(http, url, _npy(noisy), 5, lowpass_sigma_px=sigma_px)
        _refused(response, 422, "too large for 64x64 px frames")
    assert _post_stack(http, url, _npy(noisy), 5, lowpass_sigma_px="2").status_code == 200


def test_a_59_mb_json_body_is_refused(http: httpx.Client, serve: Serve) -> None:
    url = serve(create_app())
    body = b'{"z_um": [' + b"1234567.123456789012, " * (59 * 2**20 // 22) + b'0], "scores": []}'
    response = http.post(
        f"{url}/v1/focus/curve",
        content=body,
        headers={"Content-Type": "application/json"},
        timeout=60,
    )
    _refused(response, 413, "exceeds the limit of 1048576 bytes")


def test_deep_nesting_is_422_not_a_recursion_error(http: httpx.Client, serve: Serve) -> None:
    url = serve(create_app())
    depth = 100_000
    deep = b'{"z_um": ' + b"[" * depth + b"]" * depth + b', "scores": [1, 2, 1]}'
    response = http.post(
        f"{url}/v1/focus/curve", content=deep, headers={"Content-Type": "application/json"}
    )
    _refused(response, 422, "nests deeper than 32 levels")
    assert not json_depth_exceeds(b'{"a": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}', 2)
    assert json_depth_exceeds(b'{"a": [[1]]}', 2)


def test_curves_with_values_beyond_the_floats_range_are_422(
    http: httpx.Client, serve: Serve
) -> None:
    url = serve(create_app())
    cases = [
        ({"z_um": [0, 1, 2], "scores": [1, 1e308, 1]}, "scores must be finite and within"),
        ({"z_um": [0, 1e300, 2e300], "scores": [1, 2, 1]}, "z values must be finite and within"),
        ({"z_um": [0, 1, 2, 3], "scores": [1, 2, 1]}, "one score per z"),
    ]
    for body, needle in cases:
        response = http.post(f"{url}/v1/focus/curve", json=body)
        _refused(response, 422, needle)
    # integers of 400 and 5000 digits: "Input should be a valid number" (it is one) and
    # Python's "Exceeds the limit (4300 digits) ... use sys.set_int_max_str_digits()"
    for digits in (400, 5000):
        body = f'{{"z_um": [0, 1, {"9" * digits}], "scores": [1, 2, 1]}}'
        response = http.post(
            f"{url}/v1/focus/curve", content=body, headers={"content-type": "application/json"}
        )
        _refused(response, 422, "Input should be a finite number")
        assert "set_int_max_str_digits" not in response.text
    good = http.post(f"{url}/v1/focus/curve", json={"z_um": [0, 1, 2], "scores": [1, 2, 1]})
    assert good.status_code == 200 and good.json()["best_z_um"] == pytest.approx(1.0)
    too_many = {"z_um": list(range(2000)), "scores": [1.0] * 2000}
    _refused(http.post(f"{url}/v1/focus/curve", json=too_many), 422, "limit is 1001")


def test_limits_that_admit_nothing_are_a_configuration_error() -> None:
    for bad, message in (
        ({"max_frames": 2}, "max_frames must be at least 3, got 2"),  # no curve has 2
        ({"max_json_depth": 1}, "max_json_depth must be at least 2, got 1"),
        ({"max_upload_bytes": 100}, "max_upload_bytes must be at least 4096, got 100"),
        ({"body_timeout_s": 0.0}, "the body timeout must be positive"),
        ({"max_concurrent": 0}, "max_concurrent must be at least 1, got 0"),
    ):
        with pytest.raises(ValueError, match=message):
            FocusLimits(**bad)  # type: ignore[arg-type]


def test_a_stack_beyond_max_concurrent_is_a_503_and_curves_are_not_counted(
    http: httpx.Client, serve: Serve
) -> None:
    """Stacks of up to 256 MB each were read and decoded however many came at once."""
    url = serve(create_app(limits=FocusLimits(max_concurrent=1)))
    parts = urlsplit(url)
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as held:
        # a stack's upload under way: its headers and the start of its form sent
        held.sendall(
            b"POST /v1/focus/stack HTTP/1.1\r\nHost: x\r\nContent-Length: 1000\r\n"
            b"Content-Type: multipart/form-data; boundary=x\r\n\r\n--x\r\n"
            b'Content-Disposition: form-data; name="stack"; filename="s.npy"\r\n\r\n' + b"\0" * 50
        )
        frames = np.zeros((5, 8, 8), np.uint16)
        for _ in range(100):  # until the server has taken the held upload in
            busy = _post_stack(http, url, _npy(frames), 5)
            if busy.status_code == 503:
                break
            time.sleep(0.05)
        _refused(busy, 503, "busy with the most requests it takes at once (1)")
        assert busy.headers["retry-after"] == "1"
        curve = {"z_um": [0, 1, 2], "scores": [1, 2, 1]}
        assert http.post(f"{url}/v1/focus/curve", json=curve).status_code == 200
    # the held upload's connection closed: its place is free again, once the server has
    # seen it close (a request at once may still find it taken)
    frames = np.random.default_rng(0).integers(0, 4000, (5, 32, 32)).astype(np.uint16)
    answers: list[httpx.Response] = []

    def served() -> bool:
        answers.append(_post_stack(http, url, _npy(frames), 5))
        return answers[-1].status_code != 503

    assert within(served, timeout_s=5.0), answers[-1].text
    assert answers[-1].status_code in (200, 422)
