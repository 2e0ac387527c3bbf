"""The simulator's laser autofocus: the coverslip under a tile, the stage moved there."""

from __future__ import annotations

import pytest

from focustrack_core.laser import LaserSpec
from focustrack_core.v1 import instrument_pb2
from focustrack_instrument_sim.instrument import AcquisitionRefusedError
from focustrack_instrument_sim.laser import SimulatedLaser, reply
from focustrack_instrument_sim.simulated import SimulatedInstrument, simulated_instrument
from focustrack_instrument_sim.simulator_options import SimulatorOptions


def _instrument(**changes: object) -> SimulatedInstrument:
    options = SimulatorOptions.model_validate(
        {"rows": 3, "cols": 4, "height": 64, "width": 64, "seed": 2, **changes}
    )
    return simulated_instrument(options)


def test_no_laser_unless_asked() -> None:
    assert _instrument().laser is None
    assert isinstance(_instrument(laser=True).laser, SimulatedLaser)


def test_a_reading_is_the_focus_then_less_the_offset_and_moves_the_stage() -> None:
    instrument = _instrument(laser=True, laser_noise_um=0.0, drift_um_per_s=0.5)
    laser = instrument.laser
    assert laser is not None
    scope = instrument.microscope
    take = laser.read("slide-0", 1, 2)
    assert (scope.stage.x_um, scope.stage.y_um) == scope.slides["slide-0"].grid.stage_xy_um(1, 2)
    assert scope.stage.clock_s == pytest.approx(take.timing.move_s + LaserSpec().reading_s)
    truth_um, _ = scope.truth_um("slide-0")
    offset_um = laser.offsets_um("slide-0")[1, 2]
    assert take.z_um == pytest.approx(truth_um[1, 2] - offset_um)
    assert 2.0 < offset_um < 6.0 and take.sigma_um == 0.0


def test_the_reply_and_the_refusals() -> None:
    instrument = _instrument(laser=True)
    assert instrument.laser is not None
    request = instrument_pb2.LaserRequest(slide="slide-0", row=0, col=3)
    reading = reply("sim", instrument.laser, request)
    assert (reading.slide, reading.row, reading.col, reading.sigma_um) == ("slide-0", 0, 3, 0.05)
    assert reading.timing.total_s >= reading.timing.move_s > 0
    with pytest.raises(AcquisitionRefusedError, match="unknown slide"):
        instrument.laser.read("slide-9", 0, 0)
    with pytest.raises(AcquisitionRefusedError, match="outside"):
        instrument.laser.read("slide-0", 3, 0)
