"""The timing model of a scan: what each stage move, z step and exposure costs.

One model, used by the accuracy benchmark (to cost a strategy) and by the
simulated instrument (to report the time of each acquisition), so the two
always agree. Defaults are those of a typical motorised slide scanner with a
60x objective; see docs/timing.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class TimingModel:
    """Durations in seconds, speeds in um/s.

    An XY move of distance d takes a trapezoidal velocity profile
    (accelerate, cruise, decelerate) plus a settle time; every frame of a
    z-stack costs a z step with its settle, the exposure and the readout.
    """

    xy_speed_um_per_s: float = 20_000.0
    xy_accel_um_per_s2: float = 200_000.0
    xy_settle_s: float = 0.05
    z_settle_s: float = 0.01
    exposure_s: float = 0.01
    readout_s: float = 0.01

    def move_s(self, distance_um: float) -> float:
        """Time of an XY move over `distance_um`, settle included (0 for no move)."""
        if distance_um <= 0:
            return 0.0
        v, a = self.xy_speed_um_per_s, self.xy_accel_um_per_s2
        ramp_um = v * v / a  # distance spent accelerating and decelerating to full speed
        if distance_um < ramp_um:
            travel_s = 2.0 * math.sqrt(distance_um / a)
        else:
            travel_s = 2.0 * v / a + (distance_um - ramp_um) / v
        return travel_s + self.xy_settle_s

    def frame_s(self) -> float:
        """One frame of a stack: z step and settle, exposure, readout."""
        return self.z_settle_s + self.exposure_s + self.readout_s

    def stack_s(self, n_frames: int) -> float:
        """A z-stack of `n_frames` frames."""
        return n_frames * self.frame_s()
