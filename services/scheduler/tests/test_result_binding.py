"""A scan takes a focus result only for the acquisition it waits for, once (real Zenoh on
loopback, the engine's own waiting code, stand-ins for the instrument and the focus service).

The exploit: results captured during one scan of a slide, re-published during a later scan
of it after the focus moved, were taken, every one: the result key's HMAC covers the key
expression and the payload, so an old genuine result is still genuine. Each acquisition
now goes out under a fresh nonce that its frames and its result carry.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zenoh

from focustrack_client import EstimatorClient
from focustrack_core.domain import Acquisition, Purpose, ZRange
from focustrack_core.testing import within
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2
from focustrack_core.wire import keys, rpc, session
from focustrack_core.wire.trust import NONCE_BYTES, ResultSigner
from focustrack_scheduler.clients import InstrumentClient, SlideListener, refusal
from focustrack_scheduler.engine import Engine, ScanRefusedError
from focustrack_scheduler.plan import Acquire, AwaitFocus, FocusUnavailableError, Plan
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy

SLIDE = "s1"
RESULT_KEY = ResultSigner(b"r" * 32)
ACQUISITION = Acquisition(3, 1, 2, ZRange(-2.0, 0.5, 9), Purpose.SCAN, measure=True)

#: A result as it went on the bus: key expression, payload, attachment (its tag).
Sent = tuple[str, bytes, bytes]


class StandIns:
    """An instrument that answers every acquisition, and a focus service that publishes,
    before the reply, `copies` tagged results of its stack with best focus `best_z_um`;
    `replays` (results sent before) are put again first, as a replaying peer would."""

    def __init__(self, bus: zenoh.Session, echo_nonce: bool = True) -> None:
        self.bus = bus
        self.echo_nonce = echo_nonce
        self.best_z_um = 1.0
        self.copies = 1
        self.replays: list[Sent] = []
        self.sent: list[Sent] = []  # every genuine result put
        self.on_acquire: Callable[[], None] = lambda: None  # called before it replies
        self._queryable = rpc.declare_answering(bus, keys.acquire_key("sim"), self._acquire)

    def _acquire(self, query: zenoh.Query) -> instrument_pb2.AcquireReply:
        request = rpc.parse_request(query, instrument_pb2.AcquireRequest)
        z_um = [request.z_low_um + i * request.z_step_um for i in range(request.n_frames)]
        header = instrument_pb2.ZStackHeader(
            instrument="sim", slide=request.slide, row=request.row, col=request.col,
            sequence=request.sequence, z_um=z_um,
            nonce=request.nonce if self.echo_nonce else b"",
        )  # fmt: skip
        result = focus_pb2.FocusResult(
            slide=header.slide, row=header.row, col=header.col, sequence=header.sequence,
            nonce=header.nonce, metric="normalised_variance", z_um=z_um,
            scores=[1.0] * len(z_um), best_z_um=self.best_z_um, sigma_um=0.1,
        )  # fmt: skip
        key_expr = keys.focus_key(header.slide, header.row, header.col)
        payload = result.SerializeToString()
        for replayed in self.replays:
            self._put(*replayed)
        for _ in range(self.copies):
            self._put(key_expr, payload, RESULT_KEY.tag(key_expr, payload))
            self.sent.append((key_expr, payload, RESULT_KEY.tag(key_expr, payload)))
        self.on_acquire()
        return instrument_pb2.AcquireReply(header=header)

    def _put(self, key_expr: str, payload: bytes, tag: bytes) -> None:
        self.bus.put(key_expr, payload, attachment=tag)

    def close(self) -> None:
        self._queryable.undeclare()


def engine_on(
    scheduler: zenoh.Session,
    listener: SlideListener,
    out_dir: Path,
    focus_timeout_s: float = RetryPolicy.focus_timeout_s,
) -> Engine:
    """An engine on the scheduler's session, with no estimator (these plans ask none)."""
    return Engine(
        InstrumentClient(scheduler, "sim", timeout_s=10),
        listener,
        EstimatorClient("http://127.0.0.1:9"),
        ScanRecord(out_dir),
        RetryPolicy(focus_timeout_s=focus_timeout_s),
    )


def scan_once(engine: Engine) -> focus_pb2.FocusResult | None:
    """Acquire `ACQUISITION` and wait for its focus result, with the engine."""
    received: list[focus_pb2.FocusResult | None] = []

    def plan() -> Plan:
        yield Acquire(SLIDE, ACQUISITION)
        received.append((yield AwaitFocus(SLIDE, ACQUISITION)))
        return "scanned"

    engine.run(plan())
    return received[0]


def awaiting(listener: SlideListener) -> threading.Event:
    """An event set once the engine awaits a focus result (its acquisition is over)."""
    waiting = threading.Event()
    inbox_wait = listener.focus.wait

    def wait(*args: Any, **kwargs: Any) -> focus_pb2.FocusResult | None:
        waiting.set()
        return inbox_wait(*args, **kwargs)

    listener.focus.wait = wait  # type: ignore[method-assign]
    return waiting


def lost_results(engine: Engine) -> dict[str, float]:
    """The focus results the engine gave up on, by fault kind (those counted at all)."""
    counts = {
        kind: engine.metrics.registry.get_sample_value(
            "focustrack_scan_faults_total", {"kind": kind}
        )
        for kind in ("focus_timeout", "focus_lost", "focus_service_lost")
    }
    return {kind: count for kind, count in counts.items() if count}


@pytest.mark.parametrize("trust", [RESULT_KEY, None], ids=["result-key", "no-key"])
def test_a_replayed_result_is_not_taken_and_a_duplicate_is_taken_once(
    sessions: tuple[zenoh.Session, zenoh.Session], trust: ResultSigner | None, tmp_path: Path
) -> None:
    bus, scheduler = sessions
    stand_ins = StandIns(bus)
    listener = SlideListener(scheduler, SLIDE, trust)
    engine = engine_on(scheduler, listener, tmp_path, focus_timeout_s=10.0)
    try:
        time.sleep(0.5)  # let the subscription reach the stand-ins
        # A first scan: its result comes twice; the second copy is dropped.
        stand_ins.copies = 2
        first = scan_once(engine)
        assert first is not None and first.best_z_um == 1.0 and len(first.nonce) == NONCE_BYTES
        assert within(lambda: listener.n_rejected == 1)

        # The focus moved by 8 um; a peer replays the first scan's genuine results (right
        # slide, tile, sequence and frames, a valid tag) before each new one.
        stand_ins.copies, stand_ins.best_z_um = 1, 9.0
        stand_ins.replays = list(stand_ins.sent)
        second = scan_once(engine)
        assert second is not None and second.best_z_um == 9.0
        assert second.nonce not in (b"", first.nonce)
        assert within(lambda: listener.n_rejected == 3)

        # A copy after the wait is over is dropped as well.
        bus.put(*stand_ins.sent[-1][:2], attachment=stand_ins.sent[-1][2])
        assert within(lambda: listener.n_rejected == 4)
    finally:
        listener.close()
        stand_ins.close()


def test_an_instrument_that_drops_the_nonce_is_refused_at_once(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    bus, scheduler = sessions
    stand_ins = StandIns(bus, echo_nonce=False)
    listener = SlideListener(scheduler, SLIDE, RESULT_KEY)
    engine = engine_on(scheduler, listener, tmp_path)
    try:
        with pytest.raises(ScanRefusedError, match="without its nonce"):
            scan_once(engine)
    finally:
        listener.close()
        stand_ins.close()


def test_a_result_of_another_slide_tile_or_frames_is_refused_an_error_of_its_tile_taken() -> None:
    nonce = b"n" * NONCE_BYTES
    z_um = [-2.0 + 0.5 * i for i in range(9)]

    def result(**fields: object) -> focus_pb2.FocusResult:
        base: dict[str, object] = dict(
            slide=SLIDE, sequence=3, row=1, col=2, nonce=nonce, z_um=z_um
        )
        return focus_pb2.FocusResult(**(base | fields))  # type: ignore[arg-type]

    def why(refused: focus_pb2.FocusResult) -> str:
        return refusal(SLIDE, ACQUISITION, nonce, refused) or "taken"

    assert why(result()) == "taken"
    assert "nonce" in why(result(nonce=b"o" * NONCE_BYTES)) and "nonce" in why(result(nonce=b""))
    assert "tile (1, 3)" in why(result(col=3)) and "frames" in why(result(z_um=z_um[1:]))
    # the rest of a stack, read with the frame of its look one step below it, is taken
    assert why(result(z_um=[-2.5, *z_um])) == "taken"
    assert "frames" in why(result(z_um=[-3.0, -2.5, *z_um]))  # two frames more: not a look
    assert "no acquisition 4" in why(result(sequence=4)) and "slide" in why(result(slide="s2"))
    unreadable = result(z_um=[], error=common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK))
    assert why(unreadable) == "taken"  # a stack the focus service could not read


@pytest.mark.timeout(60)
def test_a_result_lost_with_the_bus_is_acquired_again_once_the_bus_is_back(
    tmp_path: Path,
) -> None:
    """The node the scheduler connects to goes down while a focus result is awaited and
    comes back on the same endpoint: the wait ends then (`session.LinkWatch`), not at
    its 60 s timeout, and the fault is counted as lost, not as a timeout."""
    endpoint = session.loopback_endpoint()
    bus = session.open_session(listen=[endpoint])
    stand_ins = StandIns(bus)
    stand_ins.copies = 0  # it answers the acquisition; the focus result never comes
    with session.open_session(connect=[endpoint]) as scheduler:
        listener = SlideListener(scheduler, SLIDE, RESULT_KEY)
        engine = engine_on(scheduler, listener, tmp_path, focus_timeout_s=60.0)
        waiting = awaiting(listener)
        received: list[focus_pb2.FocusResult | None] = []
        scan = threading.Thread(target=lambda: received.append(scan_once(engine)))
        started_s = time.monotonic()
        scan.start()
        try:
            assert waiting.wait(10)
            stand_ins.close()
            bus.close()  # the bus goes down with the result in flight ...
            assert within(lambda: not scheduler.info.peers_zid())
            bus = session.open_session(listen=[endpoint])  # ... and comes back
            scan.join(30)
            assert not scan.is_alive() and received == [None]
            assert time.monotonic() - started_s < 30  # not the 60 s timeout
            assert lost_results(engine) == {"focus_lost": 1}
        finally:
            listener.close()
            bus.close()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("dies", ["awaited", "acquiring"])
def test_a_result_lost_with_its_focus_service_is_acquired_again_once_one_is_there(
    tmp_path: Path, dies: str
) -> None:
    """The focus service dies with the result unpublished (while it is awaited, or before,
    as the stack is acquired) while the bus stays up, and one starts again: the wait ends
    then (`session.TokenWatch` on the services' liveliness tokens, from before the
    acquisition), not at its 60 s timeout, and the fault is counted as the service's."""
    endpoint = session.loopback_endpoint()
    with (
        session.open_session(listen=[endpoint]) as bus,
        session.open_session(connect=[endpoint]) as scheduler,
    ):
        stand_ins = StandIns(bus)
        stand_ins.copies = 0  # it answers the acquisition; the focus result never comes
        dying = session.open_session(connect=[endpoint])
        # a token undeclares itself once dropped: they are held here
        tokens = [dying.liveliness().declare_token(keys.alive_key("focus", "*", "dying"))]
        listener = SlideListener(scheduler, SLIDE, RESULT_KEY)
        if dies == "acquiring":  # gone, as the scan sees it, before the instrument replies

            def die() -> None:
                dying.close()
                assert within(lambda: not listener.focus_services.alive())

            stand_ins.on_acquire = die
        engine = engine_on(scheduler, listener, tmp_path, focus_timeout_s=60.0)
        waiting = awaiting(listener)
        received: list[focus_pb2.FocusResult | None] = []
        scan = threading.Thread(target=lambda: received.append(scan_once(engine)))
        try:
            assert within(lambda: bool(listener.focus_services.alive()))
            started_s = time.monotonic()
            scan.start()
            assert waiting.wait(10)
            dying.close()  # the service dies with the stack's result unpublished (if not yet) ...
            assert within(lambda: not listener.focus_services.alive())
            time.sleep(1.0)  # (none there to take the stack again: the wait goes on)
            assert scan.is_alive()
            with session.open_session(connect=[endpoint]) as started_again:  # ... and is back
                tokens.append(
                    started_again.liveliness().declare_token(
                        keys.alive_key("focus", SLIDE, "started-again")
                    )
                )
                scan.join(30)
            assert not scan.is_alive() and received == [None]
            assert time.monotonic() - started_s < 30  # not the 60 s timeout
            assert lost_results(engine) == {"focus_service_lost": 1}
        finally:
            listener.close()
            stand_ins.close()
            dying.close()


@pytest.mark.parametrize("served", [False, True], ids=["no-focus-service", "focus-service"])
def test_a_scan_without_focus_results_says_whether_a_focus_service_reads_the_slide(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path, served: bool
) -> None:
    """No result, however often the stack is taken: the error says when no focus service's
    liveliness token is on the bus for the slide (none reads its frames)."""
    bus, scheduler = sessions
    stand_ins = StandIns(bus)
    stand_ins.copies = 0  # no focus result ever comes
    focus_token = keys.alive_key("focus", "*", "focus")
    tokens = [bus.liveliness().declare_token(focus_token)] if served else []
    listener = SlideListener(scheduler, SLIDE, RESULT_KEY)
    engine = engine_on(scheduler, listener, tmp_path, focus_timeout_s=0.5)

    def plan() -> Plan:
        for attempt in (1, 2):
            yield Acquire(SLIDE, ACQUISITION, attempt)
            assert (yield AwaitFocus(SLIDE, ACQUISITION)) is None
        raise FocusUnavailableError("no focus result after 2 attempt(s).")

    try:
        assert within(lambda: len(listener.focus_services.alive()) == len(tokens))
        with pytest.raises(FocusUnavailableError) as raised:
            engine.run(plan())
    finally:
        listener.close()
        stand_ins.close()
        for token in tokens:
            token.undeclare()
    said = str(raised.value)
    assert said.startswith("no focus result after 2 attempt(s).")
    assert ("No focus service on the bus reads this slide" in said) is not served
    assert (keys.alive_pattern("focus", SLIDE) in said) is not served
