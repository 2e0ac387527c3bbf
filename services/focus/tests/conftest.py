"""Fixtures of the focus service's tests: z-stacks of a field of cells with a known focus, and
the REST app on a real uvicorn server on loopback."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import ExitStack

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from focustrack_core.serving import BackgroundServer

#: The blur of the cells in focus (px, a Gaussian's std) and how fast defocus widens it
#: (px per um): about a 60x / 0.85 objective's, on 0.1 um pixels.
IN_FOCUS_BLUR_PX = 0.6
BLUR_PX_PER_UM = 3.0
#: Photo-electrons of a pixel of background, and the camera's read noise (electrons).
BACKGROUND_ELECTRONS = 2000.0
READ_NOISE_ELECTRONS = 3.0

#: `render(size_px, z_um, truth_um, seed)`: frames (n, size_px, size_px) uint16 at z_um (n,).
Render = Callable[[int, np.ndarray, float, int], np.ndarray]


def render_cells(size_px: int, z_um: np.ndarray, truth_um: float, seed: int) -> np.ndarray:
    """A field of stained cells taken at z_um (n,), in focus at truth_um (um): frames
    (n, size_px, size_px) uint16 in 12 bits, each with its own photon and read noise.

    The cells are darker discs (radius 6-14 px) with a fine texture, on a bright
    background; defocus blurs them with a Gaussian whose std grows linearly with
    |z - truth_um|. `seed` draws the field and the noise.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size_px, 0:size_px]
    field = np.ones((size_px, size_px), np.float32)
    for _ in range(max(size_px * size_px // 800, 1)):
        (cy, cx), radius = rng.uniform(0, size_px, 2), rng.uniform(6.0, 14.0)
        field[(y - cy) ** 2 + (x - cx) ** 2 < radius**2] *= 0.55
    texture = cv2.GaussianBlur(rng.standard_normal(field.shape).astype(np.float32), (0, 0), 1.0)
    field *= 1.0 + 0.15 * texture / texture.std()
    frames = []
    for z in np.asarray(z_um, dtype=np.float64):
        blur_px = math.hypot(IN_FOCUS_BLUR_PX, BLUR_PX_PER_UM * (z - truth_um))
        image = cv2.GaussianBlur(field, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
        electrons = rng.poisson(BACKGROUND_ELECTRONS * image.astype(np.float64))
        frames.append(electrons + rng.normal(0.0, READ_NOISE_ELECTRONS, image.shape))
    return np.clip(np.rint(frames), 0, 4095).astype(np.uint16)


@pytest.fixture(scope="session")
def render() -> Render:
    """`render_cells`: stacks of a field of cells whose focus is known."""
    return render_cells


@pytest.fixture
def serve() -> Iterator[Callable[[FastAPI], str]]:
    """Serve ASGI apps on loopback for the test: `url = serve(app)`; stopped after it."""
    with ExitStack() as servers:
        yield lambda app: servers.enter_context(BackgroundServer(app)).url.rstrip("/")
