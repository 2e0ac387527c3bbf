"""A tile whose measurement's reply was lost is taken up again, not lost (real estimator)."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import numpy as np
import pytest

from focustrack.lab_sim import SimScope
from focustrack_client import EstimatorClient
from focustrack_client.models import Grid, SlideCreate
from focustrack_lab.tracker import FocusTracker, TileOrderError


class LosesReplies(httpx.HTTPTransport):
    """The network: the estimator gets the first `n_lost` measurements and answers them, but
    the answers are lost (a timeout, as behind a balancer that gave up on a slow reply)."""

    def __init__(self, n_lost: int) -> None:
        super().__init__()
        self.n_lost = n_lost

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        response = super().handle_request(request)
        if self.n_lost and request.method == "POST" and request.url.path.endswith("/measurements"):
            self.n_lost -= 1
            response.close()
            raise httpx.ReadTimeout("the estimator's reply was lost", request=request)
        return response


def test_a_tile_whose_reply_was_lost_is_taken_up_where_it_stopped(
    estimator: EstimatorClient,
    small_scope: SimScope,
    slide_of: Callable[[SimScope, str, float], SlideCreate],
) -> None:
    """The estimator recorded the tile's stack and moved on; called again, the tracker posts
    the same measurement again and gets its outcome (it used to say "the estimator expects
    (0, 1) next, not tile (0, 0)": the tile, its stack taken, had no height)."""
    base_url = str(estimator.http.base_url)
    stacks: list[np.ndarray] = []

    def acquire(z_um: np.ndarray) -> np.ndarray:
        stacks.append(z_um)
        frames = []
        for z in z_um:
            small_scope.z_um = float(z)
            frames.append(small_scope.frame())
        return np.stack(frames)

    with EstimatorClient(base_url, transport=LosesReplies(1), retry_pauses_s=()) as lossy:
        tracker = FocusTracker.create(lossy, slide_of(small_scope, "kf-2d", 0.1))
        grid = small_scope.microscope.slides[small_scope.slide].grid
        small_scope.x_um = -(grid.cols - 1) / 2 * grid.pitch_um
        small_scope.y_um = (grid.rows - 1) / 2 * grid.pitch_um
        with pytest.raises(httpx.ReadTimeout):
            tracker.focus(0, 0, acquire)
        assert len(stacks) == 1 and not tracker.tiles
        recorded = estimator.diagnostics(tracker.slide_id)

        tile = tracker.focus(0, 0, acquire)

    assert tile.n_stacks == len(stacks) and tile.n_frames == sum(map(len, stacks))
    assert tile.last is not None and tile.last.best_z_um is not None
    assert tracker.tiles == [tile]
    assert recorded.n_measured >= 1  # the lost reply's measurement had been recorded
    after = estimator.next(tracker.slide_id)
    assert (after.row, after.col) == (0, 1)  # the scan goes on from the next tile


def test_a_survey_strategy_is_refused_saying_why(estimator: EstimatorClient) -> None:
    """Its survey points come first, in their own order: the tracker said "visit the tiles
    in its serpentine order" to a loop that did."""
    config = SlideCreate(strategy="survey-bilinear", grid=Grid(rows=12, cols=12))
    tracker = FocusTracker.create(estimator, config)
    rng = np.random.default_rng(0)
    with pytest.raises(TileOrderError, match="a survey strategy visits its survey points"):
        for col in range(12):
            tracker.focus(0, col, lambda z_um: rng.random((len(z_um), 8, 8)))
