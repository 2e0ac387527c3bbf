"""Slides the tracker cannot scan are refused before any stack, and its order errors say
plainly what is wrong (real estimator)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from focustrack.lab_sim import SimScope
from focustrack_client import EstimatorClient
from focustrack_client.models import Grid, SlideCreate, ZRangePolicy
from focustrack_lab.tracker import FocusTracker, TileOrderError


def config(strategy: str = "kf-2d", **fields: Any) -> SlideCreate:
    return SlideCreate(strategy=strategy, grid=Grid(rows=2, cols=3), start_sigma_um=5.0, **fields)


#: Slides whose estimator asks for a 2-frame pair, a 1-frame look or a laser reading: the
#: tracker took such a stack, then failed to read it ("a focus curve needs at least 3
#: frames") on every retry, or posted a camera frame as a laser reading.
UNSERVABLE = {
    "short pair": (config("kf-2d-lean", params={"short_frames": 2}), "short_frames is 2"),
    "2-frame z-range": (
        config(z_range=ZRangePolicy(min_frames=2, max_frames=2)),
        "z_range.min_frames is 2",
    ),
    "look first": (config("kf-2d-lean", params={"look_first": True}), "look_first is true"),
    # As the estimator's models read them: "true" is true, "2" is 2.
    "look first as text": (
        config("kf-2d-lean", params={"look_first": "true"}),
        "look_first is true",
    ),
    "short pair as text": (config("kf-2d-lean", params={"short_frames": "2"}), "short_frames is 2"),
    "laser": (config("kf-2d-laser"), "kf-2d-laser asks for laser autofocus readings"),
}


@pytest.mark.parametrize("name", sorted(UNSERVABLE))
def test_a_slide_asking_for_what_the_tracker_cannot_read_is_refused_before_it_is_made(
    estimator: EstimatorClient, name: str
) -> None:
    slide, why = UNSERVABLE[name]
    before = len(estimator.list_slides())
    with pytest.raises(TileOrderError, match="the tracker cannot scan this slide: .*" + why):
        FocusTracker.create(estimator, slide)
    assert len(estimator.list_slides()) == before  # nothing made at the estimator


def test_an_existing_slide_is_checked_when_opened(estimator: EstimatorClient) -> None:
    slide_id = estimator.create_slide(config("kf-2d-lean", params={"short_frames": 2})).id
    with pytest.raises(TileOrderError, match="short_frames is 2"):
        FocusTracker.open(estimator, slide_id)
    assert FocusTracker.open(estimator, estimator.create_slide(config()).id).slide_id


@pytest.mark.parametrize(
    ("slide", "why"),
    [
        (config(z_range=ZRangePolicy(min_frames=2, max_frames=2)), "asks for a 2-frame stack"),
        (config("kf-2d-laser"), "asks for a laser autofocus reading"),
    ],
    ids=["2-frame stack", "laser reading"],
)
def test_an_acquisition_the_tracker_cannot_read_is_refused_before_it_is_taken(
    estimator: EstimatorClient, slide: SlideCreate, why: str
) -> None:
    """A tracker made around an unchecked slide (the constructor asks the estimator nothing)."""
    tracker = FocusTracker(estimator, estimator.create_slide(slide).id)
    taken: list[np.ndarray] = []

    def acquire(z_um: np.ndarray) -> np.ndarray:
        taken.append(z_um)
        return np.zeros((len(z_um), 16, 16))

    with pytest.raises(TileOrderError, match=f"{why} at tile \\(0, 0\\)"):
        tracker.focus(0, 0, acquire)
    assert taken == []


def test_a_tile_off_the_grid_and_a_finished_scan_are_named_as_such(
    estimator: EstimatorClient, small_scope: SimScope
) -> None:
    tracker = FocusTracker.create(estimator, config())

    def acquire(z_um: np.ndarray) -> np.ndarray:
        frames = []
        for z in z_um:
            small_scope.z_um = float(z)
            frames.append(small_scope.frame())
        return np.stack(frames)

    with pytest.raises(TileOrderError, match=r"tile \(5, 0\) is outside the 2x3 grid"):
        tracker.focus(5, 0, acquire)
    for row, col in ((0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)):  # serpentine
        tracker.focus(row, col, acquire)
    with pytest.raises(TileOrderError, match=r"^the scan is done: no tile is pending"):
        tracker.focus(0, 0, acquire)
