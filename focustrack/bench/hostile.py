"""Hostile but fair requests against the estimator and focus REST APIs.

`fire(estimator_url, focus_url)` sends each request that once cost gigabytes or
answered 500, and returns the HTTP status each got (0: the connection was closed
without an answer). A hardened service answers every one with a 4xx (or, for the
slides it may create, 201) and stays small; `focustrack bench chaos` watches the
services' memory meanwhile, and tests/test_hostile.py checks that none is a 5xx.

The requests:
- ``kf2d-bank-20``: a 578-byte POST /v1/slides of kf-2d with 20 values for each of
  its three bank parameters (8000 filters);
- ``gp-oracle-500``: gp-oracle on a 500x500 grid (its covariance: 466 GiB);
- ``kf2d-250x750``: kf-2d on the 250x750 grid of a whole 25x75 mm slide;
- ``sigma-1e-300``: a slide whose start sigma is 1e-300 um;
- ``tiff-bomb``: a zlib TIFF of 27 frames of 8192x8192 uint16 (3.6 GB decoded);
- ``json-59mb``: a 59 MB JSON body to /v1/focus/curve;
- ``json-deep``: a curve whose z_um nests 100 000 lists deep;
- ``npy-huge-shape``: a .npy whose header declares 10^18 pixels;
- ``zero-size-frames``: a stack of 5 frames of 0x8 pixels;
- ``large-lowpass``: 8x8 frames with a low-pass of 64 px;
- ``many-slides``: `n_slides` small kf-2d slides created one after another (the
  highest status seen).
"""

from __future__ import annotations

import io
import select
import socket
from collections.abc import Iterator
from urllib.parse import urlsplit

import httpx
import numpy as np

from focustrack_focus.bombs import BOMB_FRAMES, npy_with_shape, zlib_tiff_bomb

TIMEOUT_S = 120.0


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _raw_post(url: str, path: str, headers: dict[str, str], body: Iterator[bytes]) -> int:
    """POST over a plain socket, sending the body only while the server has not answered.

    httpx sends the whole body before it reads a reply, and a server that refuses
    a declared length at once closes the connection under it: this reads the early
    refusal. Returns the status, or 0 if the connection closed without one.
    """
    parts = urlsplit(url)
    lines = [f"POST {path} HTTP/1.1", f"Host: {parts.netloc}", "Connection: close"]
    lines += [f"{name}: {value}" for name, value in headers.items()]
    with socket.create_connection((parts.hostname, parts.port or 80), TIMEOUT_S) as sock:
        sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        reply = b""
        try:
            for chunk in body:
                if select.select([sock], [], [], 0)[0]:
                    break  # an answer before the body: stop sending
                sock.sendall(chunk)
        except OSError:  # closed under us: the answer may have come first
            pass
        try:
            while b"\r\n" not in reply:
                data = sock.recv(4096)
                if not data:
                    break
                reply += data
        except OSError:
            pass
    status_line = reply.split(b"\r\n", 1)[0].split()
    return int(status_line[1]) if len(status_line) > 1 and status_line[1].isdigit() else 0


def _slide(strategy: str, rows: int, cols: int, **extra: object) -> dict[str, object]:
    return {"strategy": strategy, "grid": {"rows": rows, "cols": cols}, **extra}


def fire(
    estimator_url: str,
    focus_url: str,
    *,
    estimator_token: str | None = None,
    focus_token: str | None = None,
    n_slides: int = 2000,
) -> dict[str, int]:
    """Every hostile request above against the two services; the status each got."""
    statuses: dict[str, int] = {}
    estimator_auth = {"Authorization": f"Bearer {estimator_token}"} if estimator_token else {}
    focus_auth = {"Authorization": f"Bearer {focus_token}"} if focus_token else {}
    with httpx.Client(base_url=estimator_url, headers=estimator_auth, timeout=TIMEOUT_S) as api:
        values = [round(0.1 * (i + 1), 1) for i in range(20)]
        bank = {"sigmas_um": values, "lengths_tiles": values, "tilt_sigmas_um_per_tile": values}
        slides = {
            "kf2d-bank-20": _slide("kf-2d", 146, 146, params=bank),
            "gp-oracle-500": _slide("gp-oracle", 500, 500),
            "kf2d-250x750": _slide("kf-2d", 250, 750),
            "sigma-1e-300": _slide("kf-2d", 20, 20, start_sigma_um=1e-300),
        }
        for name, body in slides.items():
            statuses[name] = api.post("/v1/slides", json=body).status_code
        many = [api.post("/v1/slides", json=_slide("kf-2d", 10, 10)) for _ in range(n_slides)]
        statuses["many-slides"] = max((r.status_code for r in many), default=0)

    with httpx.Client(base_url=focus_url, headers=focus_auth, timeout=TIMEOUT_S) as focus:

        def stack(name: str, data: bytes, n_frames: int, **form: str) -> None:
            files = {"stack": ("stack", data, "application/octet-stream")}
            fields = {"z_um": ",".join(str(float(z)) for z in range(n_frames)), **form}
            statuses[name] = focus.post("/v1/focus/stack", files=files, data=fields).status_code

        stack("tiff-bomb", zlib_tiff_bomb(), BOMB_FRAMES)
        stack("npy-huge-shape", npy_with_shape((10**6, 10**6, 10**6)), 5)
        stack("zero-size-frames", _npy(np.zeros((5, 0, 8), np.uint16)), 5)
        noisy = np.random.default_rng(0).integers(0, 4000, (5, 8, 8)).astype(np.uint16)
        stack("large-lowpass", _npy(noisy), 5, lowpass_sigma_px="64")
        depth = 100_000
        deep = b'{"z_um": ' + b"[" * depth + b"]" * depth + b', "scores": [1, 2, 1]}'
        statuses["json-deep"] = focus.post(
            "/v1/focus/curve", content=deep, headers={"Content-Type": "application/json"}
        ).status_code

    n_points = 59 * 2**20 // 20  # numbers of about 20 characters: 59 MB
    point = b"1234567.123456789012, "

    def big_json() -> Iterator[bytes]:
        yield b'{"z_um": ['
        for _ in range(n_points // 10_000):
            yield point * 10_000
        yield b'0], "scores": [1, 2, 3]}'

    length = len(b'{"z_um": [') + n_points // 10_000 * 10_000 * len(point)
    length += len(b'0], "scores": [1, 2, 3]}')
    headers = {"Content-Type": "application/json", "Content-Length": str(length), **focus_auth}
    statuses["json-59mb"] = _raw_post(focus_url, "/v1/focus/curve", headers, big_json())
    return statuses
