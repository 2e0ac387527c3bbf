"""The scheduler fetches only the frames it keeps from the instrument, takes a stack again
when the instrument no longer holds it, and fits its stacks to the travel and frame limit the
instrument states (real Zenoh sessions, an in-process instrument)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh

from focustrack_client import EstimatorClient
from focustrack_core.domain import Acquisition, Purpose, ZRange
from focustrack_core.surfaces import SurfaceSpec
from focustrack_core.wire import session
from focustrack_core.wire.trust import new_nonce
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, slides_from_seed
from focustrack_instrument_sim.service import InstrumentService
from focustrack_instrument_sim.simulated import SimulatedInstrument
from focustrack_scheduler import outputs
from focustrack_scheduler.clients import InstrumentClient, SlideListener, acquire_request
from focustrack_scheduler.engine import Engine, ScanRefusedError
from focustrack_scheduler.mosaic_store import to_uint8
from focustrack_scheduler.plan import (
    Acquire,
    DescribeSlide,
    KeepTile,
    Plan,
    SlideGeometry,
    StageLimits,
)
from focustrack_scheduler.record import ScanRecord

SLIDE = "slide-0"


@pytest.fixture
def bus(
    request: pytest.FixtureRequest,
) -> Iterator[tuple[zenoh.Session, zenoh.Session, InstrumentService]]:
    """(instrument's session, scheduler's session, the instrument): it keeps no frames
    beyond its last stack, and takes at most 64 frames a stack (the test's parameter, if
    any, instead)."""
    endpoint = session.loopback_endpoint()
    slides = slides_from_seed(5, 1, SurfaceSpec(3, 3), pitch_um=200.0)
    max_frames = getattr(request, "param", 64)
    microscope = Microscope(slides, MicroscopeSpec(height=64, width=64, max_frames=max_frames))
    with (
        session.open_session(listen=[endpoint]) as served,
        session.open_session(connect=[endpoint]) as scheduler,
    ):
        service = InstrumentService(
            SimulatedInstrument(microscope), served, "sim", keep_frames_bytes=0
        )
        service.start()
        thread = threading.Thread(target=service.serve)
        thread.start()
        try:
            yield served, scheduler, service
        finally:
            service.stop.set()
            thread.join()
            service.close()
            microscope.close()


@contextmanager
def _engine(scheduler: zenoh.Session, record: ScanRecord) -> Iterator[Engine]:
    """An engine on the bus's instrument; no estimator is asked by these tests' plans."""
    listener = SlideListener(scheduler, SLIDE)
    try:
        yield Engine(
            InstrumentClient(scheduler, "sim", timeout_s=10),
            listener,
            EstimatorClient("http://127.0.0.1:9"),
            record,
        )
    finally:
        listener.close()


def _keep_only(step: KeepTile) -> Plan:
    yield DescribeSlide("sim", SLIDE)
    yield step
    return "scanned"


def _acquisition(index: int, low_um: float) -> Acquisition:
    return Acquisition(index, 1, 2, ZRange(low_um, 0.5, 5), Purpose.SCAN, measure=True)


def test_a_kept_frame_is_fetched_and_a_stack_no_longer_held_is_taken_again(
    bus: tuple[zenoh.Session, zenoh.Session, InstrumentService], tmp_path: Path
) -> None:
    _, scheduler, service = bus
    first, second = _acquisition(1, -2.0), _acquisition(2, 0.5)

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE)
        z_um = yield Acquire(SLIDE, first)
        yield Acquire(SLIDE, second)  # the instrument now holds only this stack
        yield KeepTile(1, 2, first.index, 3, z_um[3])
        return "scanned"

    record = ScanRecord(tmp_path)
    with _engine(scheduler, record) as engine:
        assert engine.run(plan()) == "scanned"
        assert record.tally.kept == {(1, 2): pytest.approx(-0.5)}
        # A stack this engine did not take (a resumed scan's) is not taken again: no image.
        assert engine.run(_keep_only(KeepTile(0, 0, 9, 0, 0.0))) == "scanned"
        assert (0, 0) not in record.tally.kept

    # The stack was taken again for its frame: three stacks acquired, the first twice.
    assert [entry["sequence"] for entry in record.tally.acquisitions] == [1, 2, 1]
    assert record.tally.n_images == 15
    # The tile's image is that frame, of the stack taken again (the one the instrument holds).
    header, (frame,) = InstrumentClient(scheduler, "sim").frames(SLIDE, 1, 2, 1, [3])
    assert header.z_um[3] == pytest.approx(-0.5) and frame.shape == (64, 64, 3)
    mosaic = np.load(tmp_path / outputs.PARTIAL_MOSAIC)
    np.testing.assert_array_equal(mosaic[64:128, 128:192], to_uint8(frame, header.bit_depth))
    assert service.recent.budget_bytes == 0


def test_a_stack_another_scan_took_under_the_same_sequence_is_not_kept(
    bus: tuple[zenoh.Session, zenoh.Session, InstrumentService], tmp_path: Path
) -> None:
    """Another scan of the slide takes a stack of the same tile under the same sequence (at
    other heights) between this engine's stack and its keeping a frame of it: the frames the
    instrument then holds carry the other's nonce, so the engine takes its own stack again
    and keeps its frame, not the other's."""
    _, scheduler, _ = bus
    ours = _acquisition(1, -2.0)  # frames -2.0 .. 0.0
    theirs = replace(ours, z=ZRange(20.0, 0.5, 5))

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE)
        z_um = yield Acquire(SLIDE, ours)
        InstrumentClient(scheduler, "sim").acquire(acquire_request(SLIDE, theirs, new_nonce()))
        yield KeepTile(1, 2, ours.index, 3, z_um[3])
        return "scanned"

    record = ScanRecord(tmp_path)
    with _engine(scheduler, record) as engine:
        assert engine.run(plan()) == "scanned"
    assert record.tally.kept == {(1, 2): pytest.approx(-0.5)}
    assert [entry["sequence"] for entry in record.tally.acquisitions] == [1, 1]  # ours again
    header, _ = InstrumentClient(scheduler, "sim").frames(SLIDE, 1, 2, 1, [3])
    assert header.z_um[3] == pytest.approx(-0.5)  # the stack whose frame was kept is ours


def test_a_stack_fitted_to_the_limits_the_instrument_states_is_taken(
    bus: tuple[zenoh.Session, zenoh.Session, InstrumentService], tmp_path: Path
) -> None:
    """The instrument's info states its travel (+/-100 um) and frame limit (64); a stack
    beyond both, fitted to them, is taken, where as asked it is refused."""
    _, scheduler, _ = bus
    asked = Acquisition(1, 0, 0, ZRange(90.0, 0.5, 80), Purpose.SCAN, measure=False)
    taken: list[tuple[float, ...]] = []

    def plan(fitted: bool) -> Plan:
        geometry: SlideGeometry = yield DescribeSlide("sim", SLIDE)
        assert geometry.stage == StageLimits(-100.0, 100.0, 64)
        z = geometry.stage.fit(asked.z) if fitted else asked.z
        taken.append((yield Acquire(SLIDE, replace(asked, z=z), asked=asked.z)))
        return "scanned"

    with _engine(scheduler, ScanRecord(tmp_path)) as engine:
        assert engine.run(plan(fitted=True)) == "scanned"
        with pytest.raises(ScanRefusedError, match="at most 64"):
            engine.run(plan(fitted=False))
    (z_um,) = taken
    assert len(z_um) == 64 and z_um[-1] == pytest.approx(100.0) and z_um[0] >= 60.0


@pytest.mark.parametrize("bus", [1], indirect=True)
def test_an_instrument_of_one_frame_a_stack_is_refused_before_any_stack(
    bus: tuple[zenoh.Session, zenoh.Session, InstrumentService], tmp_path: Path
) -> None:
    _, scheduler, _ = bus
    refused = pytest.raises(ScanRefusedError, match="at most 1 frame a stack; a focus curve")
    with _engine(scheduler, ScanRecord(tmp_path)) as engine, refused:
        engine.run(_keep_only(KeepTile(0, 0, 9, 0, 0.0)))
