"""A real estimator service (uvicorn, SQLite) on a free loopback port, and a small slide."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from focustrack.lab_sim import SimScope
from focustrack_client import EstimatorClient
from focustrack_client.models import Grid, SlideCreate
from focustrack_core.surfaces import SurfaceSpec
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, slides_from_seed


@pytest.fixture(scope="module")
def estimator(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EstimatorClient]:
    """One service per test file: each test makes slides of its own (3 s of CPU a start)."""
    port = free_port()
    process = spawn(tmp_path_factory.mktemp("estimator") / "estimator.sqlite", port, timeout_s=120)
    try:
        with EstimatorClient(f"http://127.0.0.1:{port}") as client:
            yield client
    finally:
        process.terminate()
        process.wait(timeout=10)


@pytest.fixture
def scope() -> SimScope:
    """A 6x6 slide under a microscope with 256 x 256 frames."""
    slides = slides_from_seed(7, 1, SurfaceSpec(6, 6), pitch_um=200.0)
    spec = MicroscopeSpec(height=256, width=256)
    return SimScope(Microscope(slides, spec), "slide-0")


@pytest.fixture
def small_scope() -> SimScope:
    """A 3x3 slide under a microscope with 64 x 64 frames: a run in a second or two."""
    slides = slides_from_seed(7, 1, SurfaceSpec(3, 3), pitch_um=200.0)
    spec = MicroscopeSpec(height=64, width=64)
    return SimScope(Microscope(slides, spec), "slide-0")


@pytest.fixture
def slide_of() -> Callable[[SimScope, str, float], SlideCreate]:
    """Makes the estimator slide of a scope's slide for a strategy and a noise (um): its
    grid and depth of field, the start 5 um unsure."""

    def slide(scope: SimScope, strategy: str, noise_sigma_um: float) -> SlideCreate:
        grid = scope.microscope.slides[scope.slide].grid
        return SlideCreate(
            strategy=strategy,
            grid=Grid(rows=grid.rows, cols=grid.cols, pitch_um=grid.pitch_um),
            dof_um=scope.microscope.spec.optics.depth_of_field_um,
            noise_sigma_um=noise_sigma_um,
            start_sigma_um=5.0,
        )

    return slide


@pytest.fixture
def scope_slide(
    scope: SimScope, slide_of: Callable[[SimScope, str, float], SlideCreate]
) -> Callable[[str, float], SlideCreate]:
    """`slide_of` the 6x6 scope."""
    return lambda strategy, noise_sigma_um: slide_of(scope, strategy, noise_sigma_um)
