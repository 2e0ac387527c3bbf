"""The simulator's reflection (laser) autofocus, and its queryable's reply.

`SimulatedLaser` reads the coverslip under a tile of the microscope's slides
(`focustrack_core.laser`: the tissue's focus minus a smooth offset drawn per slide,
with the sensor's noise): the stage moves there (the clock advances by the move and
the reading's time, about a millisecond) and the drift at that moment is in the
reading, as it is in the tissue's focus. `reply` answers a `LaserRequest` on
`focustrack/v1/instrument/{name}/laser` (the service declares it where the instrument
has a laser: `--laser`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from focustrack_core.laser import LaserSpec, coverslip_offsets, laser_reading
from focustrack_core.v1 import instrument_pb2
from focustrack_instrument_sim.instrument import AcquisitionRefusedError, Refusal, StackTiming

if TYPE_CHECKING:  # the service imports this module; the microscope's imports are heavy
    from focustrack_instrument_sim.microscope import Microscope


@dataclass(frozen=True)
class LaserTake:
    """One reading: the interface's height (um), the sensor's noise (um) and its timing."""

    z_um: float
    sigma_um: float
    timing: StackTiming


class LaserSensor(Protocol):
    """What the service needs of a reflection autofocus."""

    def read(self, slide: str, row: int, col: int) -> LaserTake: ...


class SimulatedLaser:
    """The laser autofocus of a `Microscope` (see the module docstring)."""

    def __init__(self, microscope: Microscope, spec: LaserSpec, seed: int) -> None:
        self.microscope = microscope
        self.spec = spec
        self._rng = np.random.default_rng([seed, 13])
        self._offsets: dict[str, np.ndarray] = {}

    def offsets_um(self, slide: str) -> np.ndarray:
        """The slide's offsets from the coverslip to the tissue's focus, (rows, cols) um."""
        if slide not in self._offsets:
            chosen = self.microscope.slides[slide]
            seed = int(np.random.SeedSequence(chosen.specimen_seed).generate_state(1)[0])
            self._offsets[slide] = coverslip_offsets(chosen.grid.shape, seed, self.spec)
        return self._offsets[slide]

    def read(self, slide: str, row: int, col: int) -> LaserTake:
        """A reading of tile (row, col) of `slide`; AcquisitionRefusedError for an unknown
        slide or a tile off its grid."""
        if slide not in self.microscope.slides:
            raise AcquisitionRefusedError(
                Refusal.UNKNOWN_SLIDE, f"unknown slide {slide!r}", "slide"
            )
        chosen = self.microscope.slides[slide]
        if not chosen.grid.contains(row, col):
            raise AcquisitionRefusedError(
                Refusal.TILE_OUTSIDE_SLIDE,
                f"tile ({row}, {col}) is outside the slide's {chosen.grid.rows}x"
                f"{chosen.grid.cols} grid",
                "row" if not 0 <= row < chosen.grid.rows else "col",
            )
        stage = self.microscope.stage
        timing, _ = stage.acquire(*chosen.grid.stage_xy_um(row, col), 0, 0.0)
        stage.clock_s += self.spec.reading_s
        focus_um = chosen.focus_um[row, col] + stage.drift_um(stage.clock_s)
        z_um = laser_reading(
            focus_um, self.offsets_um(slide)[row, col], self.spec.noise_um, self._rng
        )
        return LaserTake(z_um, self.spec.noise_um, timing)


def reply(
    name: str, sensor: LaserSensor, request: instrument_pb2.LaserRequest
) -> instrument_pb2.LaserReading:
    """The `LaserReading` of `request` (the caller turns refusals into error replies)."""
    take = sensor.read(request.slide, request.row, request.col)
    timing = take.timing
    return instrument_pb2.LaserReading(
        instrument=name,
        slide=request.slide,
        row=request.row,
        col=request.col,
        z_um=take.z_um,
        sigma_um=take.sigma_um,
        timing=instrument_pb2.Timing(
            move_s=timing.move_s,
            exposure_s=timing.total_s - timing.move_s,
            total_s=timing.total_s,
            move_distance_um=timing.move_distance_um,
        ),
    )
