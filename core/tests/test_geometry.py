"""Scan geometry: the serpentine path, the direction of every step, tile positions."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_client import models as api
from focustrack_core.geometry import MAX_GRID_SIDE, MAX_TILES, ScanGrid, Step, Tile


def test_serpentine_alternates_row_direction() -> None:
    grid = ScanGrid(3, 4)
    path = [(t.row, t.col) for t in grid.serpentine]
    assert path == [
        (0, 0), (0, 1), (0, 2), (0, 3),
        (1, 3), (1, 2), (1, 1), (1, 0),
        (2, 0), (2, 1), (2, 2), (2, 3),
    ]  # fmt: skip
    assert len(set(path)) == grid.n_tiles


def test_steps_follow_the_path() -> None:
    grid = ScanGrid(3, 4)
    x, minus_x, y = Step.PLUS_X, Step.MINUS_X, Step.PLUS_Y
    assert list(grid.steps) == [Step.START, x, x, x, y, minus_x, minus_x, minus_x, y, x, x, x]


@pytest.mark.parametrize(("rows", "cols"), [(1, 1), (1, 5), (5, 1), (4, 7), (7, 4)])
def test_every_step_moves_one_tile_in_its_direction(rows: int, cols: int) -> None:
    grid = ScanGrid(rows, cols)
    moves = {Step.PLUS_X: (0, 1), Step.MINUS_X: (0, -1), Step.PLUS_Y: (1, 0)}
    assert grid.steps[0] is Step.START and len(grid.steps) == grid.n_tiles
    path = grid.serpentine
    for previous, tile, step in zip(path[:-1], path[1:], grid.steps[1:], strict=True):
        assert (tile.row - previous.row, tile.col - previous.col) == moves[step]
    assert sum(step is Step.PLUS_Y for step in grid.steps) == rows - 1


def test_order_index_inverts_the_path() -> None:
    grid = ScanGrid(4, 5)
    for position, tile in enumerate(grid.serpentine):
        assert grid.order_index[tile.row, tile.col] == position
    assert np.array_equal(np.sort(grid.order_index.ravel()), np.arange(grid.n_tiles))


def test_positions_and_distances_in_um() -> None:
    grid = ScanGrid(2, 3, pitch_um=250.0, origin_x_um=1000.0, origin_y_um=-50.0)
    assert grid.shape == (2, 3)
    assert grid.stage_xy_um(1, 2) == (1500.0, 200.0)
    assert grid.distance_um(Tile(0, 0), Tile(0, 2)) == 500.0
    assert grid.distance_um(Tile(0, 0), Tile(1, 1)) == pytest.approx(250.0 * np.sqrt(2))
    assert grid.contains(1, 2) and not grid.contains(2, 0) and not grid.contains(0, -1)


@pytest.mark.parametrize("kwargs", [{"rows": 0, "cols": 3}, {"rows": 2, "cols": 2, "pitch_um": 0}])
def test_invalid_grids_are_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        ScanGrid(**kwargs)


def test_the_grid_bounds_are_the_estimator_apis() -> None:
    assert (MAX_GRID_SIDE, MAX_TILES) == (api.MAX_GRID_SIDE, api.MAX_TILES)
    with pytest.raises(ValueError, match="too large"):
        ScanGrid(1, MAX_GRID_SIDE + 1)
    with pytest.raises(ValueError, match="too large"):
        ScanGrid(MAX_GRID_SIDE, MAX_GRID_SIDE)
