"""`--backend mmcore-sim`: the simulator behind pymmcore-plus's device layer gives the
simulator's frames bit for bit (its green channel), through MMCore's calls; its grid,
range and optics are the simulator's, and it knows the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    DeviceError,
    Instrument,
    PhaseTruthSource,
    Purpose,
    StackPlan,
    StackRequest,
    TruthSource,
)
from focustrack_instrument_sim.mmcore_sim import GREEN, SimulatedMMCoreInstrument
from focustrack_instrument_sim.service import InstrumentSettings, open_instrument

SLIDE = {"rows": 3, "cols": 4, "width": 96, "height": 64, "seed": 5}


def _frames(instrument: Instrument, plan: StackPlan) -> np.ndarray:
    """The frames of `plan`, (n, height, width, channels)."""
    frames = np.empty((plan.n_frames, *plan.frame.shape), plan.frame.dtype)
    for _ in instrument.acquire(plan, frames.__getitem__):
        pass
    return frames


def _stack(instrument: Instrument, request: StackRequest) -> np.ndarray:
    return _frames(instrument, instrument.plan(request))


def test_the_frames_are_the_simulators_green_channel_bit_for_bit() -> None:
    request = StackRequest("slide-0", 2, 1, -1.0, 0.5, 5, exposure_s=0.004)
    simulator = open_instrument(InstrumentSettings(backend="sim", **SLIDE))
    try:
        expected = _stack(simulator, request)[..., GREEN]
        described = simulator.describe()
    finally:
        simulator.close()
    instrument = open_instrument(InstrumentSettings(backend="mmcore-sim", **SLIDE))
    try:
        assert isinstance(instrument, SimulatedMMCoreInstrument)
        frames = _stack(instrument, request)
        assert frames.shape == (*expected.shape, 1)  # a monochrome camera
        assert np.array_equal(frames[..., 0], expected)
        # the XY stage went to the tile the simulator puts there
        assert instrument.core.getXYPosition() == pytest.approx(
            described.slides[0].grid.stage_xy_um(2, 1)
        )
        assert instrument.core.getExposure() == pytest.approx(4.0)  # ms
        description = instrument.describe()
        assert description.slides == described.slides
        assert description.z_range_um == described.z_range_um
        assert description.max_frames == described.max_frames
        assert description.optics == described.optics
        assert description.frame.channel_order == "L" and not description.hardware_sequenced
    finally:
        instrument.close()


def test_it_knows_the_truth_and_refuses_as_the_simulator() -> None:
    settings = InstrumentSettings(backend="mmcore-sim", serve_truth=True, **SLIDE)
    instrument = open_instrument(settings)
    try:
        assert isinstance(instrument, TruthSource)
        truth = instrument.truth("slide-0")
        assert truth.best_focus_um.shape == (3, 4)
        with pytest.raises(AcquisitionRefusedError, match="unknown slide"):
            instrument.truth("slide-9")
        with pytest.raises(AcquisitionRefusedError):
            instrument.plan(StackRequest("slide-0", 3, 0, 0.0, 1.0, 3))  # row 3 of 3
        _, z_high_um = instrument.describe().z_range_um
        with pytest.raises(AcquisitionRefusedError):
            instrument.plan(StackRequest("slide-0", 0, 0, z_high_um, 1.0, 3))
    finally:
        instrument.close()


def test_one_slide_only() -> None:
    with pytest.raises(ValueError, match="--slides 1"):
        open_instrument(InstrumentSettings(backend="mmcore-sim", slides=2, **SLIDE))


def test_a_camera_off_the_slide_is_a_device_error() -> None:
    """The camera images the tile under the objective; off the slide, the simulator refuses
    and the core reports the camera's error, which the backend makes a DeviceError."""
    instrument = open_instrument(InstrumentSettings(backend="mmcore-sim", **SLIDE))
    try:
        assert isinstance(instrument, SimulatedMMCoreInstrument)
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 1.0, 1))
        instrument.core.setXYPosition(-5000.0, 0.0)  # moved away behind the backend's back
        with pytest.raises(DeviceError, match=r"Camera: nothing to image here: tile .* outside"):
            _frames(instrument, plan)
    finally:
        instrument.close()


def test_a_phase_specimen_comes_through_with_the_simulators_imaging_and_phase_truth() -> None:
    phase = {**SLIDE, "specimen": "phase-blood", "serve_truth": True}
    request = StackRequest("slide-0", 1, 1, -1.0, 0.5, 3, purpose=Purpose.PHASE,
                           reference_z_um=-0.5)  # fmt: skip
    simulator = open_instrument(InstrumentSettings(backend="sim", **phase))
    try:
        expected_plan = simulator.plan(request)
        expected = _frames(simulator, expected_plan)[..., GREEN]
        assert isinstance(simulator, PhaseTruthSource)
        expected_phase = simulator.phase_truth("slide-0", 2, 1)
    finally:
        simulator.close()
    instrument = open_instrument(InstrumentSettings(backend="mmcore-sim", **phase))
    try:
        plan = instrument.plan(request)
        assert np.array_equal(_frames(instrument, plan)[..., 0], expected)
        assert (plan.purpose, plan.reference_z_um) == (Purpose.PHASE, -0.5)
        assert plan.imaging == expected_plan.imaging and plan.imaging.condenser_na == 0.2
        assert isinstance(instrument, PhaseTruthSource)
        phase_rad = instrument.phase_truth("slide-0", 2, 1).phase_rad
        assert phase_rad.shape == (64, 96) and phase_rad.max() > 0.5  # red cells
        np.testing.assert_array_equal(phase_rad, expected_phase.phase_rad)
    finally:
        instrument.close()


def test_a_stage_offset_goes_through_micro_managers_xy_stage() -> None:
    """A request's stage offset (a second pass's lateral correction) moves MMCore's XY stage
    off the tile's place, and the camera shows what the simulator shows there, bit for bit."""
    slide = {**SLIDE, "tissue_slide": True, "lateral_offset_x_um": 1.5, "lateral_offset_y_um": 0.5}
    request = StackRequest(
        "slide-0", 1, 1, -0.5, 0.5, 3, exposure_s=0.004, stage_offset_x_um=1.0,
        stage_offset_y_um=0.25,
    )  # fmt: skip
    simulator = open_instrument(InstrumentSettings(backend="sim", **slide))
    try:
        expected = _stack(simulator, request)[..., GREEN]
        x_um, y_um = simulator.describe().slides[0].grid.stage_xy_um(1, 1)
    finally:
        simulator.close()
    instrument = open_instrument(InstrumentSettings(backend="mmcore-sim", **slide))
    try:
        frames = _stack(instrument, request)
        assert np.array_equal(frames[..., 0], expected)
        assert isinstance(instrument, SimulatedMMCoreInstrument)
        assert instrument.core.getXYPosition() == pytest.approx((x_um + 1.0, y_um + 0.25))
    finally:
        instrument.close()
