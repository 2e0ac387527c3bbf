"""Scan geometry: a grid of tiles, its serpentine order and the direction of every step.

Conventions (docs/DESIGN): tiles are (row, col), 0-based; row is y, col is x.
Serpentine order: row 0 left to right, row 1 right to left, and so on. In the
filters one tile step is one unit of distance (dx = 1), so slopes are um per tile.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property

import numpy as np

#: The largest grid side and tile count a slide may have: the estimator API's own
#: (`focustrack_client.models.MAX_GRID_SIDE`, `MAX_TILES`; a test keeps them equal),
#: restated for what does not speak it (the simulated instrument's slides).
MAX_GRID_SIDE = 1000
MAX_TILES = 250_000


class Step(StrEnum):
    """Direction of the move that brought the stage to a tile."""

    START = "start"  # the first tile: no move
    PLUS_X = "+x"
    MINUS_X = "-x"
    PLUS_Y = "+y"


@dataclass(frozen=True)
class Tile:
    row: int
    col: int


@dataclass(frozen=True)
class ScanGrid:
    """A rows x cols grid of tiles, `pitch_um` apart, tile (0, 0) centred at the origin."""

    rows: int
    cols: int
    pitch_um: float = 200.0
    origin_x_um: float = 0.0
    origin_y_um: float = 0.0

    def __post_init__(self) -> None:
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"grid must have at least one tile, got {self.rows}x{self.cols}")
        if max(self.rows, self.cols) > MAX_GRID_SIDE or self.n_tiles > MAX_TILES:
            raise ValueError(
                f"grid {self.rows}x{self.cols} is too large: at most {MAX_GRID_SIDE} tiles a "
                f"side and {MAX_TILES} in all"
            )
        if not self.pitch_um > 0:
            raise ValueError(f"pitch_um must be positive, got {self.pitch_um}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def n_tiles(self) -> int:
        return self.rows * self.cols

    def contains(self, row: int, col: int) -> bool:
        return 0 <= row < self.rows and 0 <= col < self.cols

    def stage_xy_um(self, row: int, col: int) -> tuple[float, float]:
        """Stage position (x, y) in um of the centre of tile (row, col)."""
        return (self.origin_x_um + col * self.pitch_um, self.origin_y_um + row * self.pitch_um)

    def distance_um(self, a: Tile, b: Tile) -> float:
        """Euclidean stage travel between two tile centres, in um."""
        return float(np.hypot(a.row - b.row, a.col - b.col) * self.pitch_um)

    @cached_property
    def serpentine(self) -> tuple[Tile, ...]:
        """All tiles in serpentine scan order."""
        return tuple(
            Tile(row, col)
            for row in range(self.rows)
            for col in (range(self.cols) if row % 2 == 0 else range(self.cols - 1, -1, -1))
        )

    @cached_property
    def steps(self) -> tuple[Step, ...]:
        """Direction of the move onto each tile of `serpentine` (START for the first)."""
        path = self.serpentine
        directions = [Step.START]
        for previous, tile in itertools.pairwise(path):
            if tile.row != previous.row:
                directions.append(Step.PLUS_Y)
            else:
                directions.append(Step.PLUS_X if tile.col > previous.col else Step.MINUS_X)
        return tuple(directions)

    @cached_property
    def order_index(self) -> np.ndarray:
        """(rows, cols) int array: the position of each tile in serpentine order."""
        index = np.empty(self.shape, dtype=int)
        for i, tile in enumerate(self.serpentine):
            index[tile.row, tile.col] = i
        return index
