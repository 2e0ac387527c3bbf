"""The stage: travel limits, XY moves and z steps timed by `TimingModel`, thermal z drift, a clock.

The clock is simulated: every acquisition advances it by the time the move, the z
steps, the exposures and the readouts would take on the real instrument (the same
`TimingModel` the accuracy benchmark costs strategies with). The service may pace
it in real time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from focustrack_core.drift import ThermalDrift
from focustrack_core.timing import TimingModel
from focustrack_instrument_sim.instrument import StackTiming
from focustrack_instrument_sim.simulator_options import default

#: A simulated time in s: one, or an array of them.
Clock = TypeVar("Clock", float, np.ndarray)


@dataclass(frozen=True)
class StageSpec:
    """Travel limits in um (a 75 x 25 mm slide, tile (0, 0) at its corner, and a margin of
    1 mm around it for a stage sent off a tile's place; +/- 100 um of focus) and z drift."""

    x_range_um: tuple[float, float] = (-1000.0, 76_000.0)
    y_range_um: tuple[float, float] = (-1000.0, 26_000.0)
    z_range_um: tuple[float, float] = (-100.0, 100.0)
    # slow thermal z drift: focus moves by this much per second
    drift_um_per_s: float = default("drift_um_per_s")
    timing: TimingModel = field(default_factory=TimingModel)
    # warm-up settling and a random walk on top (`focustrack_core.drift`); None: neither
    thermal: ThermalDrift | None = None
    # where the slides lie against where they lay at the start, (x, y) um (a second pass
    # after lateral drift): the stage at (x, y) shows the slide's (x - dx, y - dy)
    slide_offset_um: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("x_range_um", "y_range_um", "z_range_um"):
            low, high = getattr(self, name)
            if not low < high:
                raise ValueError(f"{name} must be (low, high) with low < high, got {(low, high)}")


class Stage:
    """Where the stage is and what time the simulated clock shows (starts at x = y = 0, or the
    nearest point of its travel, t = 0)."""

    def __init__(self, spec: StageSpec) -> None:
        self.spec = spec
        self.x_um = min(max(0.0, spec.x_range_um[0]), spec.x_range_um[1])
        self.y_um = min(max(0.0, spec.y_range_um[0]), spec.y_range_um[1])
        self.clock_s = 0.0

    def drift_um(self, clock_s: Clock) -> Clock:
        """z drift of the focus at simulated time(s) `clock_s` (a float, or an array of them)."""
        thermal = self.spec.thermal
        if thermal is None:
            return self.spec.drift_um_per_s * clock_s
        if isinstance(clock_s, np.ndarray):
            return self.spec.drift_um_per_s * clock_s + thermal.array(clock_s)
        return self.spec.drift_um_per_s * clock_s + thermal.at(clock_s)

    def acquire(
        self, x_um: float, y_um: float, n_frames: int, exposure_s: float
    ) -> tuple[StackTiming, np.ndarray]:
        """Move to (x, y) and take `n_frames` frames; advance the clock.

        Returns the timing and the simulated time of the middle of each
        frame's exposure, shape (n_frames,), in s.
        """
        timing = self.spec.timing
        distance_um = math.hypot(x_um - self.x_um, y_um - self.y_um)
        move_s = timing.move_s(distance_um)
        frame_s = timing.z_settle_s + exposure_s + timing.readout_s
        mid_exposure_s = (
            self.clock_s
            + move_s
            + timing.z_settle_s
            + exposure_s / 2
            + frame_s * np.arange(n_frames)
        )
        stack = StackTiming(
            move_distance_um=distance_um,
            move_s=move_s,
            z_settle_s=n_frames * timing.z_settle_s,
            exposure_s=n_frames * exposure_s,
            readout_s=n_frames * timing.readout_s,
        )
        self.x_um, self.y_um = x_um, y_um
        self.clock_s += stack.total_s
        return stack, mid_exposure_s
