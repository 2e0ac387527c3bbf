"""With a frame key, the focus service scores only the instrument's frames (real Zenoh on
loopback, with shared memory on and off).

The exploit: on the open bus a peer without any key published its own frames for a tile
and sequence, and the focus service made results of them. Here a forger publishes a
stack for the tile, sequence and nonce of a genuine acquisition, before it, in focus 2 um
away from the genuine one: once untagged, once tagged with a key of its own. The focus
service drops and counts every forged sample, and its one result is the genuine stack's.
"""

from __future__ import annotations

import math
import queue
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh

from focustrack_core.v1 import focus_pb2, instrument_pb2
from focustrack_core.wire import keys
from focustrack_core.wire.codec import PixelPublisher, describe_pixels
from focustrack_core.wire.session import loopback_endpoint, open_session
from focustrack_core.wire.trust import FrameSigner
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.service import ZenohFocusWorker

Z_UM = np.arange(-3.0, 3.01, 0.5)
TRUTH_UM = -0.4
FORGED_TRUTH_UM = TRUTH_UM + 2.0
SIZE = 96  # frames of 96 x 96 uint16: 18432 bytes
PART_BYTES = 5000  # over the network a frame goes in 4 parts
NONCE = b"acquisition-0001"

INSTRUMENT_KEY = FrameSigner(b"i" * 32)
FORGER_KEY = FrameSigner(b"f" * 32)


@pytest.fixture(params=[True, False], ids=["shared-memory", "network"])
def bus(request: pytest.FixtureRequest) -> Iterator[tuple[zenoh.Session, zenoh.Session, bool]]:
    """(the instrument's session, the focus service's, shared memory on) on one endpoint."""
    shared_memory: bool = request.param
    endpoint = loopback_endpoint()
    with (
        open_session(listen=[endpoint], shared_memory=shared_memory) as instrument,
        open_session(connect=[endpoint], shared_memory=shared_memory) as focus,
    ):
        yield instrument, focus, shared_memory


def publish(publisher: PixelPublisher, pixels: np.ndarray) -> int:
    """Publish the frames of `pixels` (n, h, w) for tile (2, 3) of s1, sequence 5 and
    `NONCE`; the number of samples they went in."""
    header = instrument_pb2.ZStackHeader(
        instrument="sim", slide="s1", row=2, col=3, sequence=5, nonce=NONCE,
        z_um=Z_UM.tolist(), pixel_size_um=0.1, channel_order="L", bit_depth=12,
    )  # fmt: skip
    stack = pixels[..., None]
    describe_pixels(header, stack)
    shared, network = publisher.n_shared, publisher.n_network
    for index in range(len(stack)):
        publisher.put_frame(keys.zframe_key("s1", 2, 3), header, index, stack[index])
    parts = math.ceil(stack[0].nbytes / PART_BYTES)
    return (publisher.n_shared - shared) + (publisher.n_network - network) * parts


def test_forged_frames_never_become_a_result(
    bus: tuple[zenoh.Session, zenoh.Session, bool], render: Callable[..., np.ndarray]
) -> None:
    instrument, focus, shared_memory = bus
    pool_bytes = 1 << 20 if shared_memory else 0
    worker = ZenohFocusWorker(focus, FocusSettings(), na=0.85, frame_signer=INSTRUMENT_KEY)
    results: queue.Queue[focus_pb2.FocusResult] = queue.Queue()
    subscriber = instrument.declare_subscriber(
        keys.focus_pattern("s1"),
        lambda sample: results.put(focus_pb2.FocusResult.FromString(sample.payload.to_bytes())),
    )
    try:
        time.sleep(0.5)  # let the subscriptions reach each other
        forged = render(SIZE, Z_UM, FORGED_TRUTH_UM, 1)
        untagged = PixelPublisher(instrument, pool_bytes, PART_BYTES)
        wrong_key = PixelPublisher(instrument, pool_bytes, PART_BYTES, FORGER_KEY)
        n_forged = publish(untagged, forged) + publish(wrong_key, forged)
        genuine = PixelPublisher(instrument, pool_bytes, PART_BYTES, INSTRUMENT_KEY)
        publish(genuine, render(SIZE, Z_UM, TRUTH_UM, 2))
        if shared_memory:  # the frames went as the test means them to
            assert genuine.n_shared == len(Z_UM) and genuine.n_network == 0
        else:
            assert genuine.n_shared == 0 and genuine.n_network == len(Z_UM)

        result = results.get(timeout=20)
        assert (result.sequence, result.nonce) == (5, NONCE)
        assert not result.HasField("error")
        assert result.best_z_um == pytest.approx(TRUTH_UM, abs=0.15)  # not the forger's
        assert worker.analyser.n_untagged == n_forged
        with pytest.raises(queue.Empty):
            results.get(timeout=1.0)  # and no other result
    finally:
        subscriber.undeclare()
        worker.close()
    assert worker.n_published == 1
