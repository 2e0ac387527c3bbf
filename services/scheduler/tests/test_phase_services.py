"""A scan's phase stacks and the phase services that read them (real Zenoh on loopback,
the engine's own code, stand-ins for the instrument and the phase services).

Each phase service holds a liveliness token while it reads frames (`keys.alive_key`). With
none there a tile's phase stack waits up to the phase timeout for one (a service restarting
is back within seconds), and when none comes it is not acquired (no one would reconstruct
it), nor is one awaited again until one is there: the scan used to take each stack and
wait out the timeout on every tile. One that dies with the result unpublished ends the
wait once another is there, which is given the stack again (once). The scan goes on
without the last `phase_in_flight` results (it images the next tile while the phase
service reconstructs) and awaits the rest before it ends; a scan that stops keeps the
tiles whose phase was still to come without it.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zenoh

from focustrack_client import EstimatorClient
from focustrack_core.domain import ZRange
from focustrack_core.testing import within
from focustrack_core.v1 import instrument_pb2, phase_pb2
from focustrack_core.wire import codec, keys, rpc, session
from focustrack_scheduler import outputs
from focustrack_scheduler.clients import InstrumentClient, SlideListener
from focustrack_scheduler.engine import Engine, ScanRefusedError
from focustrack_scheduler.plan import AcquirePhase, DescribeSlide, PhaseStacks, Plan
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy

SLIDE = "s1"
PHASE_STACK = AcquirePhase(SLIDE, 1, 2, ZRange(-1.0, 0.25, 9), 0.0, sequence=2**40 + 5)


class Instrument:
    """Answers the info query (a 3x3 slide) and every acquisition, counting them. With
    `phase_after_s`, it also stands in for a phase service: each phase stack's result (a
    2x4x4 field of its sequence) is published that long after the stack, and `events`
    says in which order stacks were acquired and results published."""

    def __init__(
        self,
        bus: zenoh.Session,
        phase_after_s: float | None = None,
        stage: instrument_pb2.InstrumentInfo | None = None,
    ) -> None:
        self.acquired = 0
        self._stage = stage or instrument_pb2.InstrumentInfo()  # its travel, depth of field
        self.events: list[str] = []
        self._bus = bus
        self._phase_after_s = phase_after_s
        self._timers: list[threading.Timer] = []
        self._queryables = [
            rpc.declare_answering(bus, keys.info_key("sim"), self._info),
            rpc.declare_answering(bus, keys.acquire_key("sim"), self._acquire),
        ]

    def _info(self, query: zenoh.Query) -> instrument_pb2.InstrumentInfo:
        slide = instrument_pb2.SlideInfo(slide=SLIDE, rows=3, cols=3, pitch_um=100.0)
        info = instrument_pb2.InstrumentInfo(instrument="sim", slides=[slide])
        info.MergeFrom(self._stage)
        return info

    def _acquire(self, query: zenoh.Query) -> instrument_pb2.AcquireReply:
        request = rpc.parse_request(query, instrument_pb2.AcquireRequest)
        self.acquired += 1
        z_um = [request.z_low_um + i * request.z_step_um for i in range(request.n_frames)]
        header = instrument_pb2.ZStackHeader(
            instrument="sim", slide=request.slide, row=request.row, col=request.col,
            sequence=request.sequence, z_um=z_um, nonce=request.nonce,
            purpose=request.purpose,
        )  # fmt: skip
        self.events.append(f"acquired {request.sequence}")
        if self._phase_after_s is not None:
            timer = threading.Timer(self._phase_after_s, self._publish_phase, (header,))
            self._timers.append(timer)
            timer.start()
        return instrument_pb2.AcquireReply(header=header)

    def _publish_phase(self, header: instrument_pb2.ZStackHeader) -> None:
        result = phase_pb2.PhaseResult(
            instrument="sim", slide=header.slide, row=header.row, col=header.col,
            sequence=header.sequence, nonce=header.nonce, shape=(2, 4, 4),
            dtype=codec.PHASE_DTYPE,
        )  # fmt: skip
        field = np.full((2, 4, 4), header.sequence % 1000, dtype=codec.PHASE_DTYPE)
        self.events.append(f"published {header.sequence}")
        self._bus.put(
            keys.phase_key(header.slide, header.row, header.col),
            field.tobytes(),
            attachment=result.SerializeToString(),
        )

    def close(self) -> None:
        for timer in self._timers:
            timer.cancel()
        for queryable in self._queryables:
            queryable.undeclare()


@pytest.fixture
def bus() -> Iterator[tuple[str, zenoh.Session, zenoh.Session]]:
    """(the endpoint, the stand-ins' session that listens on it, the scheduler's)."""
    endpoint = session.loopback_endpoint()
    with (
        session.open_session(listen=[endpoint]) as stand_ins,
        session.open_session(connect=[endpoint]) as scheduler,
    ):
        yield endpoint, stand_ins, scheduler


def engine_for(
    scheduler: zenoh.Session, listener: SlideListener, out_dir: Path, policy: RetryPolicy
) -> Engine:
    return Engine(
        InstrumentClient(scheduler, "sim", timeout_s=10),
        listener,
        EstimatorClient("http://127.0.0.1:9"),  # these plans ask no estimator
        ScanRecord(out_dir),
        policy,
    )


def take_phase(
    scheduler: zenoh.Session,
    listener: SlideListener,
    out_dir: Path,
    stacks: int = 1,
    phase_timeout_s: float = 60.0,
    phase_in_flight: int = 1,
) -> Engine:
    """Describe the slide and take `stacks` phase stacks with an engine; the engine, once
    its plan is over."""
    policy = RetryPolicy(phase_timeout_s=phase_timeout_s, phase_in_flight=phase_in_flight)
    engine = engine_for(scheduler, listener, out_dir, policy)

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE)
        for index in range(stacks):
            yield replace(PHASE_STACK, sequence=PHASE_STACK.sequence + index)
        return "scanned"

    engine.run(plan())
    engine.record.close()
    return engine


def logged_phase(out_dir: Path) -> list[dict]:
    """The scan log's phase entries."""
    lines = (out_dir / outputs.LOG_FILE).read_text().splitlines()
    return [entry for entry in map(json.loads, lines) if entry["event"] == "phase"]


@pytest.mark.parametrize(
    ("step_um", "refused", "warned"),
    [(1000.0, "fit in the instrument's z travel (-100 to 100 um) only once", None),
     (0.001, None, "reach less than 0.2 of the objective's depth of field (0.9 um)"),
     (None, None, None)],
)  # fmt: skip
def test_phase_stacks_the_stage_cuts_to_one_frame_are_refused_and_ones_too_near_focus_said(
    bus: tuple[str, zenoh.Session, zenoh.Session],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    step_um: float | None,
    refused: str | None,
    warned: str | None,
) -> None:
    """Frames 1000 um apart on a stage of 200 um of travel were cut to 1 on every tile, each
    stack taken and refused by the phase service, and the scan ended with no phase and
    exit 0; a step of 0.001 um gave a flat phase, said nowhere."""
    _, stand_ins, scheduler = bus
    stage = instrument_pb2.InstrumentInfo(
        z_min_um=-100.0, z_max_um=100.0, max_frames=64, depth_of_field_um=0.9
    )
    instrument = Instrument(stand_ins, stage=stage)
    engine = engine_for(scheduler, SlideListener(scheduler, SLIDE), tmp_path, RetryPolicy())

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE, PhaseStacks(11, step_um))
        return "described"

    try:
        if refused is not None:
            with pytest.raises(ScanRefusedError, match=re.escape(refused)):
                engine.run(plan())
        else:
            engine.run(plan())
    finally:
        engine.listener.close()
        engine.record.close()
        instrument.close()
    assert instrument.acquired == 0
    said = [record.getMessage() for record in caplog.records if record.levelname == "WARNING"]
    near_focus = [line for line in said if "too near focus" in line]
    if warned is None:
        assert near_focus == [], said
    else:
        assert len(near_focus) == 1 and warned in near_focus[0], said


@pytest.mark.timeout(60)
def test_with_no_phase_service_one_is_awaited_once_and_no_phase_stack_is_taken(
    bus: tuple[str, zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    _, stand_ins, scheduler = bus
    instrument = Instrument(stand_ins)
    # a focus service's token is not a phase service's
    token = stand_ins.liveliness().declare_token(keys.alive_key("focus", "*", "focus"))
    listener = SlideListener(scheduler, SLIDE, phase=True)
    try:
        take_phase(scheduler, listener, tmp_path, stacks=3, phase_timeout_s=2.0)
    finally:
        listener.close()
        instrument.close()
        token.undeclare()
    assert instrument.acquired == 0
    entries = logged_phase(tmp_path)
    assert [entry["n_frames"] for entry in entries] == [0, 0, 0]
    assert all(entry["file"] is None for entry in entries)
    assert [entry["error"] for entry in entries] == [
        "no phase service on the bus reads this slide (waited 2 s)",
        *["no phase service on the bus reads this slide (waited 0 s)"] * 2,
    ]


@pytest.mark.timeout(60)
def test_a_phase_service_that_comes_is_given_the_stack_and_its_loss_retakes_it_once(
    bus: tuple[str, zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    """No phase service at the stack's turn: the stack waits for one, is acquired once it
    is there, and when it dies with the result unpublished and one starts again, the stack
    is taken again for that one, at once, not at the 60 s timeout. When that one dies too,
    the tile has no phase."""
    endpoint, stand_ins, scheduler = bus
    instrument = Instrument(stand_ins)
    listener = SlideListener(scheduler, SLIDE, phase=True)
    assert listener.phase_services is not None
    phase_services = listener.phase_services
    done: list[Engine] = []
    scan = threading.Thread(target=lambda: done.append(take_phase(scheduler, listener, tmp_path)))
    dying = session.open_session(connect=[endpoint])
    tokens = []  # held: a token undeclares itself once dropped
    try:
        started_s = time.monotonic()
        scan.start()
        time.sleep(1.0)
        assert instrument.acquired == 0  # none there: the stack waits
        tokens.append(dying.liveliness().declare_token(keys.alive_key("phase", "*", "dying")))
        assert within(lambda: instrument.acquired == 1)  # one came: it gets the stack
        dying.close()  # ... and dies with the stack's result unpublished
        assert within(lambda: not phase_services.alive())
        # None there: the wait goes on, as through a router's restart, where every token
        # goes and comes back, and a phase computed meanwhile still comes.
        time.sleep(1.0)
        assert scan.is_alive() and instrument.acquired == 1
        for name in ("started-again", "third"):
            with session.open_session(connect=[endpoint]) as service:
                tokens.append(
                    service.liveliness().declare_token(keys.alive_key("phase", "*", name))
                )
                if name == "started-again":  # the stack is taken again for it ...
                    assert within(lambda: instrument.acquired == 2)
                else:  # ... which dies too: the tile has no phase
                    scan.join(30)
            assert within(lambda: not phase_services.alive())
        assert not scan.is_alive() and time.monotonic() - started_s < 30  # not the 60 s
    finally:
        listener.close()
        instrument.close()
        dying.close()
    (engine,) = done
    lost = engine.metrics.registry.get_sample_value(
        "focustrack_scan_faults_total", {"kind": "phase_service_lost"}
    )
    assert lost == 2 and instrument.acquired == 2
    (entry,) = logged_phase(tmp_path)
    assert entry["n_frames"] == 9 and "its phase service went" in entry["error"]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("in_flight", [1, 0])
def test_the_scan_takes_the_next_stack_while_the_last_is_reconstructed_and_keeps_every_phase(
    bus: tuple[str, zenoh.Session, zenoh.Session], tmp_path: Path, in_flight: int
) -> None:
    """A phase service that takes 1.5 s a stack. With one result in flight the second stack
    is acquired before the first result is out, and the scan still ends with all three
    kept; with none in flight each stack waits for the one before."""
    _, stand_ins, scheduler = bus
    instrument = Instrument(stand_ins, phase_after_s=1.5)
    token = stand_ins.liveliness().declare_token(keys.alive_key("phase", "*", "phase"))
    listener = SlideListener(scheduler, SLIDE, phase=True)
    try:
        take_phase(scheduler, listener, tmp_path, stacks=3, phase_in_flight=in_flight)
    finally:
        listener.close()
        instrument.close()
        token.undeclare()
    first, second = PHASE_STACK.sequence, PHASE_STACK.sequence + 1
    order = instrument.events
    assert (order.index(f"acquired {second}") < order.index(f"published {first}")) == (
        in_flight == 1
    )
    entries = logged_phase(tmp_path)
    assert [entry["sequence"] for entry in entries] == [first, second, second + 1]
    assert all(entry["error"] is None and entry["file"] for entry in entries)


@pytest.mark.timeout(60)
def test_a_scan_that_stops_keeps_the_tiles_whose_phase_was_to_come_without_it(
    bus: tuple[str, zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    _, stand_ins, scheduler = bus
    instrument = Instrument(stand_ins)  # publishes no result: the stack's is still to come
    token = stand_ins.liveliness().declare_token(keys.alive_key("phase", "*", "phase"))
    listener = SlideListener(scheduler, SLIDE, phase=True)
    engine = engine_for(scheduler, listener, tmp_path, RetryPolicy(phase_timeout_s=60.0))

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE)
        yield PHASE_STACK
        raise RuntimeError("the operator stopped the scan")

    started_s = time.monotonic()
    try:
        with pytest.raises(RuntimeError, match="operator"):
            engine.run(plan())
    finally:
        engine.record.close()
        listener.close()
        instrument.close()
        token.undeclare()
    assert time.monotonic() - started_s < 30  # the result is not awaited
    (entry,) = logged_phase(tmp_path)
    assert entry["n_frames"] == 9 and entry["file"] is None
    assert entry["error"] == "the scan stopped before its phase result came"
