"""What a slide may be: the largest grid, and the cost budget of one slide and of the live ones.

The limits are service settings (`EstimatorSettings`); a slide over them is
refused at creation with a SlideError naming the setting.
"""

from __future__ import annotations

from dataclasses import dataclass

from focustrack_client import models as api
from focustrack_estimator.errors import SlideError
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.strategy import Cost


@dataclass(frozen=True)
class GridLimits:
    """The largest grid a slide may have: tiles per side and in all.

    Memory grows with the grid: kf-2d keeps (3 + 2 cols)^2 floats per member
    model (145 MB for 18 members at 500 columns), every strategy a few maps of
    rows x cols floats and the history a record per acquisition.
    """

    max_side: int
    max_tiles: int

    @classmethod
    def of(cls, settings: EstimatorSettings) -> GridLimits:
        return cls(settings.max_grid_side, settings.max_grid_tiles)

    def check(self, grid: api.Grid) -> None:
        """Raise a SlideError naming the limit if `grid` exceeds it."""
        if max(grid.rows, grid.cols) > self.max_side or grid.rows * grid.cols > self.max_tiles:
            raise SlideError(
                f"grid {grid.rows}x{grid.cols} ({grid.rows * grid.cols} tiles) exceeds this "
                f"service's limit of {self.max_side} tiles per side and {self.max_tiles} tiles "
                "(settings --max-grid-side, --max-grid-tiles)",
                ("body", "grid"),
            )


@dataclass(frozen=True)
class Budget:
    """What one slide may cost, and what the live slides together may hold.

    A slide is refused at creation when its strategy's projected peak memory or
    compute per tile exceeds `max_slide_bytes` or `max_tile_s`. Live slides are
    evicted, least recently used first, when there are more than `max_live_slides`
    or their projected bytes add up to more than `max_live_bytes`; an evicted slide
    is rebuilt from its snapshot and log on its next request.
    """

    max_slide_bytes: int
    max_tile_s: float
    max_live_slides: int
    max_live_bytes: int

    @classmethod
    def of(cls, settings: EstimatorSettings) -> Budget:
        return cls(
            settings.max_slide_bytes,
            settings.max_tile_seconds,
            settings.max_live_slides,
            settings.max_live_bytes,
        )

    def check(self, config: api.SlideCreate, cost: Cost) -> None:
        """Raise a SlideError saying which limit the slide's projected `cost` exceeds."""
        where = f"strategy {config.strategy!r} on a {config.grid.rows}x{config.grid.cols} grid"
        if cost.peak_bytes > self.max_slide_bytes:
            raise SlideError(
                f"{where} with these parameters is projected to need {cost.peak_bytes / 2**20:.0f} "
                f"MiB; this service allows {self.max_slide_bytes / 2**20:.0f} MiB per slide "
                "(setting --max-slide-bytes): use a smaller grid or bank",
                ("body",),
            )
        if cost.seconds_per_tile > self.max_tile_s:
            raise SlideError(
                f"{where} with these parameters is projected to need {cost.seconds_per_tile:.3g} s "
                f"of computation per tile; this service allows {self.max_tile_s:g} s "
                "(setting --max-tile-seconds): use a smaller grid or bank",
                ("body",),
            )

    def over(self, n_live: int, live_bytes: int) -> bool:
        """Whether `n_live` slides projected to hold `live_bytes` together exceed the budget."""
        return n_live > self.max_live_slides or live_bytes > self.max_live_bytes
