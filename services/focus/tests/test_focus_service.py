"""The focus service on real Zenoh (loopback): the frames of a z-stack, published one by one,
come back as a FocusResult."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence

import httpx
import numpy as np
import pytest
import zenoh

from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2
from focustrack_core.wire import keys
from focustrack_core.wire.codec import PixelPublisher, describe_pixels, frame_header, raw_payload
from focustrack_core.wire.session import AliveTokens, free_port, loopback_endpoint, open_session
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.service import FrameAnalyser, ZenohFocusWorker

Z_UM = np.arange(-3.0, 3.01, 0.5)
TRUTH_UM = -0.4
PART_BYTES = 5000  # frames of 96 x 96 uint16 go in 4 parts


@pytest.fixture
def instrument() -> Iterator[tuple[zenoh.Session, str]]:
    """The listening peer (the instrument's side) and its endpoint."""
    endpoint = loopback_endpoint()
    session = open_session(listen=[endpoint])
    yield session, endpoint
    session.close()


def publish_stack(
    session: zenoh.Session,
    pixels: np.ndarray,
    z_um,
    sequence: int,
    order: Sequence[int] | None = None,
    purpose: instrument_pb2.AcquisitionPurpose = instrument_pb2.ACQUISITION_PURPOSE_FOCUS,
    slide: str = "s1",
) -> None:
    """Publish the frames of `pixels` (n, h, w, channels) of tile (2, 3) of `slide` one by
    one, in `order` (0..n-1)."""
    header = instrument_pb2.ZStackHeader(
        instrument="sim",
        slide=slide,
        row=2,
        col=3,
        sequence=sequence,
        z_um=list(z_um),
        pixel_size_um=0.1,
        channel_order="L",
        bit_depth=12,
        purpose=purpose,
    )
    describe_pixels(header, pixels)
    publisher = PixelPublisher(session, part_bytes=PART_BYTES)
    for index in range(len(pixels)) if order is None else order:
        publisher.put_frame(keys.zframe_key(slide, 2, 3), header, index, pixels[index])


def collect(session: zenoh.Session) -> tuple[zenoh.Subscriber, queue.Queue]:
    results: queue.Queue = queue.Queue()
    subscriber = session.declare_subscriber(
        keys.focus_pattern("s1"),
        lambda sample: results.put(
            (str(sample.key_expr), focus_pb2.FocusResult.FromString(sample.payload.to_bytes()))
        ),
    )
    return subscriber, results


def test_stack_in_focus_result_out_and_bad_stack_gets_an_error(
    instrument, render: Callable[..., np.ndarray]
) -> None:
    publisher, endpoint = instrument
    service = open_session(connect=[endpoint])
    worker = ZenohFocusWorker(service, FocusSettings(), na=0.85)
    subscriber, results = collect(publisher)
    try:
        time.sleep(0.5)  # let the subscriptions reach each other
        frames = render(96, Z_UM, TRUTH_UM, 3)
        # two frames while the slide has no learnt curve: not a stack the service can read
        publish_stack(publisher, frames[:2, ..., None], Z_UM[:2], sequence=6)
        _, refused = results.get(timeout=20)
        assert refused.sequence == 6 and not refused.HasField("best_z_um")
        assert refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
        assert "at least 3" in refused.error.message

        publish_stack(publisher, frames[..., None], Z_UM, sequence=7, order=range(12, -1, -1))
        key, result = results.get(timeout=20)
        assert key == "focustrack/v1/focus/s1/2/3"
        assert (result.slide, result.row, result.col, result.sequence) == ("s1", 2, 3, 7)
        assert result.instrument == "sim" and result.metric == "normalised_variance"
        assert result.HasField("best_z_um") and result.HasField("sigma_um")
        assert result.best_z_um == pytest.approx(TRUTH_UM, abs=0.15)
        assert list(result.z_um) == pytest.approx(Z_UM.tolist()) and len(result.scores) == 13
        assert not result.HasField("error") and result.compute_time_s > 0

        # that stack taught the slide's curve: two frames now are a pair, read with it
        publish_stack(publisher, frames[5:7, ..., None], Z_UM[5:7], sequence=8)
        _, pair = results.get(timeout=20)
        assert pair.sequence == 8 and not pair.HasField("error") and len(pair.scores) == 2
    finally:
        subscriber.undeclare()
        worker.close()
        service.close()
    assert worker.n_published == 3


def test_focus_services_of_two_scanners_each_answer_their_own_slides_once(
    instrument, render: Callable[..., np.ndarray]
) -> None:
    publisher, endpoint = instrument
    services = [open_session(connect=[endpoint]) for _ in range(2)]
    workers = [
        ZenohFocusWorker(session, FocusSettings(), na=0.85, slides=slides)
        for session, slides in zip(services, ("scanner-1-*", "scanner-2-$*"), strict=True)
    ]
    results: queue.Queue = queue.Queue()
    subscriber = publisher.declare_subscriber(
        keys.focus_pattern(), lambda sample: results.put(str(sample.key_expr))
    )
    slides = ("scanner-1-slide-0", "scanner-2-slide-0", "scanner-1-slide-1", "scanner-3-slide-0")
    # what a scheduler of each slide watches: the liveliness tokens of its focus services
    alive = {slide: AliveTokens(publisher, keys.alive_pattern("focus", slide)) for slide in slides}
    try:
        time.sleep(0.5)  # let the subscriptions reach each other
        first, second = (
            [keys.alive_key("focus", pattern, str(session.info.zid()))]
            for session, pattern in zip(services, ("scanner-1-*", "scanner-2-*"), strict=True)
        )
        assert [sorted(alive[slide].alive()) for slide in slides] == [first, second, first, []]
        frames = render(96, Z_UM, TRUTH_UM, 4)[..., None]
        for sequence, slide in enumerate(slides):
            publish_stack(publisher, frames, Z_UM, sequence=sequence, slide=slide)
        answered = sorted(results.get(timeout=20) for _ in range(3))
        time.sleep(1.0)  # time for a second answer to any of them, or one to scanner 3's
        assert results.empty()
        for worker in workers:
            worker.close()
        time.sleep(0.5)
        assert not any(tokens.alive() for tokens in alive.values())  # closed: no token left
    finally:
        subscriber.undeclare()
        for tokens in alive.values():
            tokens.close()
        for worker, session in zip(workers, services, strict=True):
            worker.close()  # (again, where the test got that far)
            session.close()
    assert answered == sorted(keys.focus_key(slide, 2, 3) for slide in slides[:3])
    assert [worker.n_published for worker in workers] == [2, 1]


def test_phase_stacks_are_not_focus_stacks_the_service_ignores_them(
    instrument, render: Callable[..., np.ndarray]
) -> None:
    publisher, endpoint = instrument
    service = open_session(connect=[endpoint])
    worker = ZenohFocusWorker(service, FocusSettings(), na=0.85)
    subscriber, results = collect(publisher)
    try:
        time.sleep(0.5)  # let the subscriptions reach each other
        frames = render(96, Z_UM, TRUTH_UM, 5)[..., None]
        publish_stack(
            publisher, frames, Z_UM, sequence=9, purpose=instrument_pb2.ACQUISITION_PURPOSE_PHASE
        )
        publish_stack(publisher, frames, Z_UM, sequence=10)
        # one worker takes the frames in order: the phase stack's came first, and got nothing
        _, result = results.get(timeout=20)
        assert result.sequence == 10 and result.HasField("best_z_um")
        assert results.empty()
    finally:
        subscriber.undeclare()
        worker.close()
        service.close()
    assert worker.n_published == 1 and worker.analyser.n_not_focus == len(Z_UM) * 4


def test_the_focus_command_runs_zenoh_and_http_in_one_process(
    http: httpx.Client, instrument, render: Callable[..., np.ndarray]
) -> None:
    publisher, endpoint = instrument
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "focustrack_focus",
            "--port",
            str(port),
            "--connect",
            endpoint,
        ],
        env=os.environ | {"PYTHONUNBUFFERED": "1"},
    )
    subscriber, results = collect(publisher)
    try:
        for _ in range(200):
            assert process.poll() is None, "the focus service exited"
            try:  # HTTP answers first; "ok" once its Zenoh session is open and subscribed
                if http.get(f"http://127.0.0.1:{port}/healthz").json()["status"] == "ok":
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        else:
            pytest.fail("the focus service did not come up on HTTP and Zenoh")
        time.sleep(0.5)  # let its subscription reach the instrument's side
        curve = http.post(
            f"http://127.0.0.1:{port}/v1/focus/curve",
            json={"z_um": [0, 1, 2, 3, 4], "scores": [1, 2, 4, 2, 1]},
        )
        assert curve.status_code == 200 and curve.json()["best_z_um"] == pytest.approx(2.0)
        frames = render(96, Z_UM, TRUTH_UM, 4)
        publish_stack(publisher, frames[..., None], Z_UM, sequence=1)
        _, result = results.get(timeout=20)
        assert result.best_z_um == pytest.approx(TRUTH_UM, abs=0.15)
    finally:
        subscriber.undeclare()
        process.terminate()
        process.wait(10)


class _Clock:
    """A clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def _frame_samples(
    pixels: np.ndarray, sequence: int, clock_s: float, z_um: np.ndarray = Z_UM
) -> list[tuple[bytes | bytearray, bytes]]:
    header = instrument_pb2.ZStackHeader(
        slide="s1",
        row=2,
        col=3,
        sequence=sequence,
        z_um=list(z_um),
        clock_s=clock_s,
        pixel_size_um=0.1,
        channel_order="L",
    )
    describe_pixels(header, pixels)
    return [
        (raw_payload(pixels[i]), frame_header(header, i, pixels[i]).SerializeToString())
        for i in range(len(pixels))
    ]


def test_frame_analyser_answers_on_the_last_frame_and_tells_acquisitions_apart(
    render: Callable[..., np.ndarray],
) -> None:
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
    analyser = FrameAnalyser(FocusSettings(), na=0.85, clock=_Clock())  # none expires
    key = keys.zframe_key("s1", 2, 3)
    first, again = _frame_samples(frames, 4, 1.0), _frame_samples(frames, 4, 2.0)
    # a stack taken again (same sequence, later clock) interleaved with the first one
    assert [analyser.add(key, *sample) for sample in first[:5]] == [None] * 5
    assert [analyser.add(key, *sample) for sample in again[:-1]] == [None] * 12
    done = analyser.add(key, *again[-1])
    assert done is not None and done.sequence == 4 and done.HasField("best_z_um")
    assert [analyser.add(key, *sample) for sample in first[5:-1]] == [None] * 7
    first_done = analyser.add(key, *first[-1])
    assert first_done is not None and first_done.best_z_um == done.best_z_um  # same pixels
    # a frame that cannot be read ends its stack with one error; the rest are ignored
    bad = _frame_samples(frames, 5, 3.0)
    refused = analyser.add(key, bad[0][0][:-2], bad[0][1])
    assert refused is not None and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert all(analyser.add(key, *sample) is None for sample in bad[1:])
    # so does a frame whose first part was lost
    payload, attachment = _frame_samples(frames, 6, 4.0)[0]
    second_part = instrument_pb2.ZFrameHeader.FromString(attachment)
    second_part.parts, second_part.part_offset = 2, PART_BYTES
    lost = analyser.add(key, payload[PART_BYTES:], second_part.SerializeToString())
    assert lost is not None and lost.sequence == 6 and "a part was lost" in lost.error.message


def test_a_signed_frame_on_zenoh_ends_its_stack_with_an_error_naming_it(
    render: Callable[..., np.ndarray],
) -> None:
    """Background-subtracted frames: the metrics divide by the mean, so they are refused."""
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None].astype(np.float32)
    frames[2] -= 2.0 * frames[2].mean()  # its mean now minus what it was
    analyser = FrameAnalyser(FocusSettings(), na=0.85, clock=_Clock())
    key = keys.zframe_key("s1", 2, 3)
    samples = _frame_samples(frames, 4, 1.0)
    assert [analyser.add(key, *sample) for sample in samples[:2]] == [None, None]
    refused = analyser.add(key, *samples[2])
    assert refused is not None and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert "frame 2 has a mean intensity of -" in refused.error.message
    assert "intensities (raw counts)" in refused.error.message
    assert all(analyser.add(key, *sample) is None for sample in samples[3:])  # answered once


def test_a_look_and_the_rest_of_its_stack_are_answered_as_one_curve(
    render: Callable[..., np.ndarray],
) -> None:
    """A tile's lowest frame taken alone (a look), then its other frames: the look is
    answered at once, the rest with the curve of all of them, as the whole stack is."""
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
    analyser = FrameAnalyser(FocusSettings(), na=0.85, clock=_Clock())
    key = keys.zframe_key("s1", 2, 3)
    whole = _frame_samples(frames, 4, 1.0)
    assert all(analyser.add(key, *sample) is None for sample in whole[:-1])
    whole_result = analyser.add(key, *whole[-1])
    (look_sample,) = _frame_samples(frames[:1], 5, 2.0, Z_UM[:1])
    look = analyser.add(key, *look_sample)
    assert look is not None and list(look.z_um) == [Z_UM[0]] and not look.flags  # in view
    assert analyser.open_bytes > 0  # the look is held for the rest of its stack
    rest = _frame_samples(frames[1:], 6, 3.0, Z_UM[1:])
    assert all(analyser.add(key, *sample) is None for sample in rest[:-1])
    joined = analyser.add(key, *rest[-1])
    assert joined is not None and whole_result is not None and joined.sequence == 6
    assert list(joined.z_um) == list(Z_UM) and joined.best_z_um == whole_result.best_z_um
    assert analyser.open_bytes == 0
    # the rest of a stack whose look came on another tile is not joined to it: its two
    # frames are read alone, as a pair (the slide's curve is learnt from the stacks above)
    analyser.add(keys.zframe_key("s1", 2, 4), *_frame_samples(frames[:1], 7, 4.0, Z_UM[:1])[0])
    alone = [
        analyser.add(key, *sample) for sample in _frame_samples(frames[1:3], 8, 5.0, Z_UM[1:3])
    ]
    assert alone[0] is None and alone[1] is not None and not alone[1].HasField("error")
    assert list(alone[1].z_um) == list(Z_UM[1:3])


def test_open_stacks_stay_within_the_budget_and_are_freed_after_the_timeout(
    render: Callable[..., np.ndarray],
) -> None:
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
    key = keys.zframe_key("s1", 2, 3)
    probe = FrameAnalyser(FocusSettings(), na=0.85)
    assert probe.add(key, *_frame_samples(frames, 1, 0.0)[0]) is None
    stack_bytes = probe.open_bytes  # one open stack: its curve, a whole frame and its images
    assert frames[0].nbytes < stack_bytes < 4 * frames[0].nbytes

    clock = _Clock()
    analyser = FrameAnalyser(FocusSettings(), 0.85, int(2.5 * stack_bytes), 10.0, clock=clock)
    # stacks whose frames never all come (whole frames: each kept by its stack)
    for sequence in (1, 2):
        assert analyser.add(key, *_frame_samples(frames, sequence, 0.0)[0]) is None
    assert analyser.open_bytes == 2 * stack_bytes
    refused = analyser.add(key, *_frame_samples(frames, 3, 0.0)[0])
    assert refused is not None and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert "budget" in refused.error.message and analyser.n_refused == 1
    assert analyser.open_bytes == 2 * stack_bytes  # nothing of the refused stack is held
    clock.now_s = 6.0
    assert analyser.add(key, *_frame_samples(frames, 2, 0.0)[1]) is None  # stack 2 goes on
    held_bytes = analyser.open_bytes
    clock.now_s = 10.5
    analyser.expire()  # stack 1: 10.5 s without a frame
    assert analyser.n_expired == 1 and analyser.open_bytes == held_bytes - stack_bytes
    clock.now_s = 16.5
    analyser.expire()
    assert analyser.n_expired == 2 and analyser.open_bytes == 0  # nothing a peer sent stays
    # a frame in parts that stop coming expires too
    payload, attachment = _frame_samples(frames, 4, 0.0)[0]
    first_part = instrument_pb2.ZFrameHeader.FromString(attachment)
    first_part.parts = 2
    assert analyser.add(key, payload[:PART_BYTES], first_part.SerializeToString()) is None
    assert analyser.open_bytes == frames[0].nbytes
    clock.now_s = 27.0
    analyser.expire()
    assert analyser.open_bytes == 0


def test_a_frame_larger_than_its_instrument_takes_is_refused_before_any_allocation(
    render: Callable[..., np.ndarray],
) -> None:
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
    sizes = {"sim": frames[0].nbytes}
    analyser = FrameAnalyser(FocusSettings(), 0.85, frame_bytes_of=sizes.get)
    key = keys.zframe_key("s1", 2, 3)
    # a peer declares frames of 2 GiB, to come in parts of 1 MiB (its first part in hand)
    header = instrument_pb2.ZStackHeader(
        instrument="sim", slide="s1", row=2, col=3, sequence=9, z_um=list(Z_UM),
        dtype="<u2", shape=[len(Z_UM), 32768, 32768, 1],
    )  # fmt: skip
    part = instrument_pb2.ZFrameHeader(stack=header, index=0, parts=2048)
    refused = analyser.add(key, bytes(1 << 20), part.SerializeToString())
    assert refused is not None and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert "frames of 2147483648 bytes declared; instrument 'sim' takes frames of " in (
        refused.error.message
    )
    assert analyser.open_bytes == 0 and analyser.n_refused == 1
    # its later parts are ignored; an instrument whose size is not known is bounded by the budget
    part.part_offset = 1 << 20
    assert analyser.add(key, bytes(1 << 20), part.SerializeToString()) is None
    part.stack.instrument, part.stack.sequence = "other", 10
    part.part_offset = 0
    over = analyser.add(key, bytes(1 << 20), part.SerializeToString())
    assert over is not None and "does not fit" in over.error.message
    assert analyser.open_bytes == 0 and analyser.n_refused == 2


def test_the_worker_learns_the_instruments_frame_size_and_expires_stacks_on_its_own(
    instrument, render: Callable[..., np.ndarray]
) -> None:
    publisher, endpoint = instrument
    info = instrument_pb2.InstrumentInfo(
        instrument="sim", width=96, height=96, channel_order="L", bit_depth=12
    )
    info_key = keys.info_key("sim")
    queryable = publisher.declare_queryable(
        info_key, lambda query: query.reply(info_key, info.SerializeToString())
    )
    service = open_session(connect=[endpoint])
    worker = ZenohFocusWorker(service, FocusSettings(), 0.85, open_frame_timeout_s=0.5)
    subscriber, results = collect(publisher)
    try:
        time.sleep(0.5)  # let the subscriptions reach each other
        frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
        publish_stack(publisher, frames, Z_UM, sequence=1)  # the first frame asks for info
        _, result = results.get(timeout=20)
        assert result.sequence == 1 and not result.HasField("error")
        larger = render(128, Z_UM, TRUTH_UM, 3)[..., None]  # 32 KiB frames, not 18 KiB
        publish_stack(publisher, larger, Z_UM, sequence=2)
        _, refused = results.get(timeout=20)
        assert refused.sequence == 2 and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
        assert "instrument 'sim' takes frames of 18432 bytes" in refused.error.message
        # a stack whose frames stop coming is freed by the worker, with no frame to wake it
        publish_stack(publisher, frames, Z_UM, sequence=3, order=range(4))
        deadline_s = time.monotonic() + 10
        while worker.analyser.n_expired == 0 and time.monotonic() < deadline_s:
            time.sleep(0.05)
        assert worker.analyser.n_expired == 1 and worker.analyser.open_bytes == 0
    finally:
        subscriber.undeclare()
        queryable.undeclare()
        worker.close()
        service.close()


def test_a_frame_whose_header_gives_its_stack_other_heights_ends_it_with_an_error(
    render: Callable[..., np.ndarray],
) -> None:
    """Frame 0 said 13 frames, frame 1 of the same acquisition 3: it was placed among the
    13, and the stack was never answered."""
    frames = render(96, Z_UM, TRUTH_UM, 3)[..., None]
    analyser = FrameAnalyser(FocusSettings(), na=0.85, clock=_Clock())
    key = keys.zframe_key("s1", 2, 3)
    samples = _frame_samples(frames, 4, 1.0)
    assert analyser.add(key, *samples[0]) is None
    payload, attachment = samples[1]
    other = instrument_pb2.ZFrameHeader.FromString(attachment)
    del other.stack.z_um[3:]
    other.stack.shape[0] = 3
    refused = analyser.add(key, payload, other.SerializeToString())
    assert refused is not None and refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert "frame 1's header gives its stack 3 frames at other heights" in refused.error.message
