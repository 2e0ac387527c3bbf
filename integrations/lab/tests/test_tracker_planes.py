"""The tracker passes on the frames a tile keeps where one image is too unsure (real estimator)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from focustrack.lab_sim import SimScope
from focustrack_client import EstimatorClient
from focustrack_client.models import SlideCreate
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.tracker import FocusTracker


@pytest.mark.slow
def test_a_focus_measure_too_noisy_for_the_depth_of_field_gets_several_frames_to_keep(
    estimator: EstimatorClient, scope: SimScope, scope_slide: Callable[[str, float], SlideCreate]
) -> None:
    grid = scope.microscope.slides[scope.slide].grid
    dof_um = scope.microscope.spec.optics.depth_of_field_um
    slide = scope_slide("kf-2d-lean", 1.5)
    # A measure whose peak strays 1.5 um from the focus (as the thesis' noise): its sigma says so.
    noisy = FocusSettings(peak=PeakSettings(systematic_sigma_um=1.5))
    tracker = FocusTracker.create(estimator, slide, noisy)

    def acquire(z_um: np.ndarray) -> np.ndarray:
        frames = []
        for z in z_um:
            scope.z_um = float(z)
            frames.append(scope.frame())
        return np.stack(frames)

    for col in range(grid.cols):  # the first row: the least known, the most unsure
        scope.x_um = (col - (grid.cols - 1) / 2) * grid.pitch_um
        scope.y_um = (grid.rows - 1) / 2 * grid.pitch_um
        tracker.focus(0, col, acquire)

    kept = [tile for tile in tracker.tiles if tile.planes_um]
    assert kept, [tile.sigma_um for tile in tracker.tiles]
    for tile in kept:
        planes = np.array(tile.planes_um)
        assert 3 <= planes.size <= 5 and np.all(np.diff(planes) > 0)
        assert np.all(np.diff(planes) <= dof_um + 1e-9)  # their depths of field join
        assert planes[0] <= tile.z_um <= planes[-1]


def test_a_tile_index_of_another_type_and_frames_that_are_no_array_are_named(
    estimator: EstimatorClient, scope: SimScope, scope_slide: Callable[[str, float], SlideCreate]
) -> None:
    """numpy integers are tile indices; a str is refused before any stack (it was "expects
    (0, 0) next, not tile (0, 0)"); None for frames is a ValueError, not an AttributeError
    deep in the focus maths."""
    tracker = FocusTracker.create(estimator, scope_slide("kf-2d", 1.5), FocusSettings())
    taken: list[int] = []

    def acquire(z_um: np.ndarray) -> None:
        taken.append(len(z_um))
        return None

    with pytest.raises(TypeError, match="row must be an integer, got '0'"):
        tracker.focus("0", 0, acquire)  # type: ignore[arg-type]
    assert taken == []  # refused before any stack
    with pytest.raises(ValueError, match="acquire must give the stack's frames"):
        tracker.focus(np.int64(0), np.int64(0), acquire)  # type: ignore[arg-type]
    assert taken  # a numpy integer reached the stack
