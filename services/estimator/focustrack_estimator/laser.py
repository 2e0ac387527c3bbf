"""`kf-2d-laser`: a reflection (laser) autofocus fused with the image measurements.

A laser autofocus reads the coverslip interface in about a millisecond
(`focustrack_core.laser`); the tissue's focal plane lies an unknown offset from it
that varies slowly over the slide. So on each tile the strategy first asks for a
laser reading (purpose `laser`: no image), and models

    focus(r, c, t) = laser(r, c, t) + offset(r, c),

the offset a smooth field learned by `kf-2d`'s strip-filter bank (`RowBankFilter`:
the offset in place of the surface). The drift needs no time state: the glass moves
with it, and the reading carries it. A tile's prior is the reading plus the offset's
prediction, with the variances of both (the reading's sigma, or `laser_sigma_um`);
the risk rule (`lean.choose_stack`) then images the tile once at that prior where it
is sure enough, and measures a short stack only where it is not (the first tiles,
and wherever the offset bends). A measurement z corrects the offset field with
z - laser (variance R + the reading's) and the tile's focus as a scalar update.
The smoothed layers are the readings plus the smoothed offsets.

The slide's start needs no blind search: the instrument's calibration of the offset
(`offset_um` +/- `offset_sigma_um` from slide to slide; the simulator's 4 +/- 0.4 um,
`focustrack_core.laser.LaserSpec`) is taken as a measurement of the first tile's offset,
so the first tile's prior is its reading plus the calibration, about 0.4 um unsure where
the slide's start height is 10 um unsure, and the lean rule measures it with a short
stack instead of a coarse search of 13-15 frames. The bank's tilts are the offset's
(`tilt_sigmas_um_per_tile`, 0.03 and 0.3 um/tile: the offset's own gradient, its spread
over its correlation length, and ten times it), not a surface's (kf-2d's 0.3 and 1.5),
so the tiles after the first widen from it by what an offset can do. Heights in um.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field

from focustrack_core.domain import (
    Acquisition,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRangePolicy,
)
from focustrack_core.geometry import Tile
from focustrack_core.laser import LaserSpec
from focustrack_estimator.filter_params import (
    LeanParams,
    MaxKeptPlanes,
    RiskOutOfFocus,
    SkipModelTemperature,
)
from focustrack_estimator.lean_scan import DEFAULT_RISK, MAX_KEPT_PLANES
from focustrack_estimator.serpentine import Gaussian
from focustrack_estimator.spatial import BankGrid, RowBankFilter, RowBankParams, kf_2d_cost
from focustrack_estimator.strategy import Cost, StrategyEntry


class Kf2dLaserParams(RowBankParams, LeanParams):
    """kf-2d-laser: a laser reading on every tile, the offset to the tissue learned by kf-2d's
    bank, each tile's frames chosen by the risk rule."""

    risk_out_of_focus: RiskOutOfFocus = DEFAULT_RISK
    max_kept_planes: MaxKeptPlanes = MAX_KEPT_PLANES
    # The bank's own weights: its tiles' priors are a reading each plus the offset, whose
    # members differ little; tempered (kf-2d-lean's 3) the demo's laser scan took 1.36
    # frames a tile against 1.21, every tissue tile in focus either way.
    skip_model_temperature: SkipModelTemperature = 1.0
    laser_sigma_um: float = Field(
        0.05, gt=0.0, description="Std of a laser reading that comes without its own sigma, um"
    )
    laser_reading_s: float = Field(
        0.001, ge=0.0, description="Time of one laser reading (the scan's clock), s"
    )
    tilt_sigmas_um_per_tile: BankGrid = Field(
        (0.03, 0.3),
        description="The members' prior std of each tilt of the offset's plane, um/tile: the "
        "offset's own gradient (its spread over its correlation length, 0.4 um over about 14 "
        "tiles) and ten times it (a coverslip's wedge)",
    )
    offset_um: float = Field(
        LaserSpec.offset_um,
        description="The instrument's calibrated offset from the laser's reading to the "
        "tissue's focus, over slides, um (the simulator's: `focustrack_core.laser.LaserSpec`)",
    )
    offset_sigma_um: float = Field(
        LaserSpec.offset_sigma_um,
        gt=0.0,
        description="Its spread from slide to slide, um: the prior of a slide's offset",
    )


class LaserFilter(RowBankFilter):
    """kf-2d's bank over the offset from the laser's reading to the focus (module docstring)."""

    def __init__(self, settings: SlideSettings, params: Kf2dLaserParams) -> None:
        super().__init__(settings, params, params, name="kf-2d-laser")
        # the instrument's calibration of the offset, taken as a measurement of the first
        # tile's: its prior is the calibration's, not the slide's unknown start height, and
        # the tiles after it widen from there by the bank's field and tilt; the members'
        # weights are the bank's own (the calibration tells none of them apart)
        self.x[:, 0] = params.offset_um  # the plane's offset (state 0): no innovation then
        self._update(self.grid.serpentine[0], params.offset_um, params.offset_sigma_um**2)
        self.log_weights[:] = 0.0
        self.laser_sigma_um = params.laser_sigma_um
        self.laser_reading_s = params.laser_reading_s
        self.laser_um = np.full(self.grid.shape, np.nan)  # each tile's reading
        self.laser_var_um2 = np.full(self.grid.shape, np.nan)
        self._read_at = -1  # the serpentine position of the last reading
        self._last_reading_um = settings.start_z_um

    def _plan(self) -> Acquisition | None:
        position = self._position
        if position in (self.grid.n_tiles, self._read_at):  # read: the tile's own stacks
            return super()._plan()
        tile = self.grid.serpentine[position]
        return self._acquisition(
            tile.row,
            tile.col,
            ZRangePolicy.single(self._last_reading_um, self.settings.policy.z_step_um),
            Purpose.LASER,
            measure=True,
        )

    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        if acquisition.purpose != Purpose.LASER:
            return super()._take(acquisition, measurement)
        tile = Tile(acquisition.row, acquisition.col)
        self.clock.advance_by(self.grid, tile, self.laser_reading_s)
        self._read_at = self._position
        if measurement.z_um is None or not measurement.is_observation:
            return Outcome(tile.row, tile.col, accepted=False)  # no glass seen: images decide
        sigma_um = measurement.sigma_um or self.laser_sigma_um
        self.laser_um[tile.row, tile.col] = self._last_reading_um = measurement.z_um
        self.laser_var_um2[tile.row, tile.col] = sigma_um**2
        return Outcome(tile.row, tile.col, accepted=True)

    def _reading(self, tile: Tile) -> tuple[float, float]:
        """The tile's reading and its variance; without one, the last reading, as unsure as
        the slide's start."""
        reading_um = self.laser_um[tile.row, tile.col]
        if math.isnan(reading_um):
            return self._last_reading_um, self.settings.start_sigma_um**2
        return float(reading_um), float(self.laser_var_um2[tile.row, tile.col])

    def _focus_members(self, tile: Tile) -> tuple[np.ndarray, np.ndarray]:
        offset_um, offset_var_um2 = self._members(tile)
        reading_um, reading_var_um2 = self._reading(tile)
        return offset_um + reading_um, offset_var_um2 + reading_var_um2

    def _predict(self, tile: Tile) -> Gaussian:
        offset = super()._predict(tile)
        reading_um, reading_var_um2 = self._reading(tile)
        return Gaussian(reading_um + offset.mean_um, offset.var_um2 + reading_var_um2)

    def _correct(self, tile: Tile, prior: Gaussian, z_um: float | None, R_um2: float) -> Gaussian:
        reading_um, reading_var_um2 = self._reading(tile)
        if z_um is None:
            super()._correct(tile, prior, None, R_um2)
            return prior
        super()._correct(tile, prior, z_um - reading_um, R_um2 + reading_var_um2)
        gain = prior.var_um2 / (prior.var_um2 + R_um2)
        return Gaussian(prior.mean_um + gain * (z_um - prior.mean_um), (1 - gain) * prior.var_um2)

    def _smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        mean_um, var_um2 = super()._smoothed()
        reached = len(mean_um)
        reading_um, reading_var_um2 = self.laser_um[:reached], self.laser_var_um2[:reached]
        return mean_um + reading_um, var_um2 + reading_var_um2


def kf_2d_laser_cost(settings: SlideSettings, params: Kf2dLaserParams) -> Cost:
    """kf-2d's with the offset's bank (the readings: two more floats a tile)."""
    return kf_2d_cost(settings, params)


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "kf-2d-laser": StrategyEntry(Kf2dLaserParams, LaserFilter, kf_2d_laser_cost),
}
