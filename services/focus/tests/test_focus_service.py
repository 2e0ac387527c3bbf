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
from focustrack_core.wire.session import free_port, loopback_endpoint, open_session
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
) -> None:
    """Publish the frames of `pixels` (n, h, w, channels) one by one, in `order` (0..n-1)."""
    header = instrument_pb2.ZStackHeader(
        instrument="sim",
        slide="s1",
        row=2,
        col=3,
        sequence=sequence,
        z_um=list(z_um),
        pixel_size_um=0.1,
        channel_order="L",
        bit_depth=12,
    )
    describe_pixels(header, pixels)
    publisher = PixelPublisher(session, part_bytes=PART_BYTES)
    for index in range(len(pixels)) if order is None else order:
        publisher.put_frame(keys.zframe_key("s1", 2, 3), header, index, pixels[index])


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
        publish_stack(publisher, frames[..., None], Z_UM, sequence=7, order=range(12, -1, -1))
        key, result = results.get(timeout=20)
        assert key == "focustrack/v1/focus/s1/2/3"
        assert (result.slide, result.row, result.col, result.sequence) == ("s1", 2, 3, 7)
        assert result.instrument == "sim" and result.metric == "normalised_variance"
        assert result.HasField("best_z_um") and result.HasField("sigma_um")
        assert result.best_z_um == pytest.approx(TRUTH_UM, abs=0.15)
        assert list(result.z_um) == pytest.approx(Z_UM.tolist()) and len(result.scores) == 13
        assert not result.HasField("error") and result.compute_time_s > 0

        # two frames only: not a stack the service can read; the reply says so
        publish_stack(publisher, frames[:2, ..., None], Z_UM[:2], sequence=8)
        _, refused = results.get(timeout=20)
        assert refused.sequence == 8 and not refused.HasField("best_z_um")
        assert refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
        assert "at least 3" in refused.error.message
    finally:
        subscriber.undeclare()
        worker.close()
        service.close()
    assert worker.n_published == 2


def test_the_focus_command_runs_zenoh_and_http_in_one_process(
    instrument, render: Callable[..., np.ndarray]
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
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        else:
            pytest.fail("the focus service did not answer on HTTP")
        curve = httpx.post(
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


def _frame_samples(
    pixels: np.ndarray, sequence: int, clock_s: float
) -> list[tuple[bytes | bytearray, bytes]]:
    header = instrument_pb2.ZStackHeader(
        slide="s1",
        row=2,
        col=3,
        sequence=sequence,
        z_um=list(Z_UM),
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
    analyser = FrameAnalyser(FocusSettings(), na=0.85)
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
