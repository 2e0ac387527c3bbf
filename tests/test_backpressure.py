"""Back pressure: the instrument's bounded queue answers BUSY, and the scheduler backs off.

The exploit: the acquire queue was unbounded, so 80 queued 64-frame acquisitions made a
normal acquisition wait behind all of them (17 s). Now at most `--queue-depth` wait for
the stage and the rest are refused at once with ERROR_CODE_BUSY; the scheduler's retry
policy (exponential back-off) asks again, and its acquisition is rendered after at most
the stack under way and the queued ones, not after 80.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.session import loopback_endpoint, open_session
from focustrack_scheduler.clients import InstrumentClient
from focustrack_scheduler.retry import RetryPolicy, instrument_retryable

pytestmark = pytest.mark.slow  # the instrument in its own process

QUEUE_DEPTH = 2
FLOOD = 80
NORMAL = 10_000  # the normal acquisition's sequence number


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    endpoint = loopback_endpoint()
    command = [
        sys.executable, "-m", "focustrack", "serve", "instrument", "--listen", endpoint,
        "--rows", "2", "--cols", "2", "--width", "64", "--height", "64",
        "--queue-depth", str(QUEUE_DEPTH),
    ]  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.DEVNULL)
    try:
        with open_session(connect=[endpoint], connect_timeout_s=60) as probe:
            client = InstrumentClient(probe, "sim")
            RetryPolicy().retrying(60, instrument_retryable, "info")(
                lambda: client.info(timeout_s=1.0)
            )
        yield endpoint
    finally:
        process.terminate()
        assert process.wait(timeout=30) == 0


def request(sequence: int, n_frames: int) -> instrument_pb2.AcquireRequest:
    return instrument_pb2.AcquireRequest(
        slide="slide-0", row=0, col=0, z_low_um=-3.0, z_step_um=0.1, n_frames=n_frames,
        sequence=sequence,
    )  # fmt: skip


def test_a_flood_of_big_acquisitions_gets_busy_and_a_normal_one_is_served_next(
    endpoint: str,
) -> None:
    started: list[int] = []  # sequence of each stack, in the order its first frame came
    lock = threading.Lock()
    assembler = codec.FrameAssembler()

    def on_frame(sample: zenoh.Sample) -> None:
        frame = assembler.add_sample(sample)
        if frame is not None and frame[0].index == 0:
            with lock:
                started.append(frame[0].stack.sequence)

    with (
        open_session(connect=[endpoint]) as flooder,
        open_session(connect=[endpoint]) as scheduler,
    ):
        watcher = scheduler.declare_subscriber(keys.zframe_pattern("slide-0"), on_frame)
        time.sleep(0.5)  # let the subscription reach the instrument
        acquire_key = keys.acquire_key("sim")
        flood = [
            flooder.get(
                acquire_key,
                payload=request(sequence, 64).SerializeToString(),
                encoding=rpc.protobuf_encoding(instrument_pb2.AcquireRequest),
                timeout=120,
            )
            for sequence in range(FLOOD)
        ]
        client = InstrumentClient(scheduler, "sim", timeout_s=120)
        policy = RetryPolicy(backoff_initial_s=0.05, backoff_max_s=0.5)
        busy_seen: list[int] = []

        def acquire() -> instrument_pb2.AcquireReply:
            try:
                return client.acquire(request(NORMAL, 5))
            except rpc.RemoteError as error:
                busy_seen.append(error.error.code)
                raise

        reply = policy.retrying(120, instrument_retryable, "normal acquisition")(acquire)
        assert reply.header.sequence == NORMAL and len(reply.header.z_um) == 5

        codes = []
        for replies in flood:
            for answer in replies:
                codes.append(
                    common_pb2.ERROR_CODE_UNSPECIFIED
                    if answer.ok is not None
                    else rpc.error_of(answer.err).code
                )
        watcher.undeclare()
    busy = codes.count(common_pb2.ERROR_CODE_BUSY)
    served = codes.count(common_pb2.ERROR_CODE_UNSPECIFIED)
    assert busy + served == FLOOD
    # Taken: the stack under way and the queue, and one more for each stack the stage
    # finished while the flood was still coming in (a few at most).
    assert served <= QUEUE_DEPTH + 3
    with lock:
        before_normal = started.index(NORMAL)
    assert before_normal <= served  # the normal one waited for those only, not for 80
    assert all(code == common_pb2.ERROR_CODE_BUSY for code in busy_seen)
