"""`focustrack-instrument-sim --tissue-slide` over real Zenoh on loopback: the truth says
what lies in each tile, and a request's prior comes back in its stack's header."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Iterator

import pytest
import zenoh
from instrument_process import wait_until_it_answers

from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc, session

SIZE = 128


@pytest.fixture(scope="module")
def client() -> Iterator[zenoh.Session]:
    endpoint = session.loopback_endpoint()
    command = [
        sys.executable, "-m", "focustrack_instrument_sim", "--listen", endpoint,
        "--name", "sim", "--seed", "5", "--rows", "6", "--cols", "7", "--tissue-slide",
        "--overlap", "0.2", "--width", str(SIZE), "--height", str(SIZE), "--serve-truth",
    ]  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    try:
        with session.open_session(connect=[endpoint], connect_timeout_s=60) as opened:
            wait_until_it_answers(opened, "sim", process)
            yield opened
    finally:
        process.terminate()
        assert process.wait(timeout=20) == 0


def test_the_truth_says_what_lies_in_each_tile(client: zenoh.Session) -> None:
    truth = rpc.call(client, keys.truth_key("sim", "slide-0"), instrument_pb2.AcquireRequest(),
                     instrument_pb2.SlideTruth)  # fmt: skip
    n = truth.rows * truth.cols
    assert n == 42 and len(truth.empty) == len(truth.tissue_share) == len(truth.dust_z_um) == n
    assert any(truth.empty) and not all(truth.empty)
    for focus, dust in zip(truth.best_focus_um, truth.dust_z_um, strict=True):
        assert math.isnan(dust) or 10.0 <= dust - focus <= 170.0
    info = rpc.call(client, keys.info_key("sim"), instrument_pb2.AcquireRequest(),
                    instrument_pb2.InstrumentInfo)  # fmt: skip
    assert info.slides[0].pitch_um == pytest.approx(round(0.8 * SIZE) * info.pixel_size_um)


def test_a_requests_prior_comes_back_in_its_header(client: zenoh.Session) -> None:
    request = instrument_pb2.AcquireRequest(
        slide="slide-0", row=2, col=3, z_low_um=-1.0, z_step_um=0.5, n_frames=3, sequence=1,
        prior_z_um=-0.25, prior_sigma_um=0.7,
    )  # fmt: skip
    reply = rpc.call(client, keys.acquire_key("sim"), request, instrument_pb2.AcquireReply)
    assert (reply.header.prior_z_um, reply.header.prior_sigma_um) == (-0.25, 0.7)
    request.ClearField("prior_z_um")
    request.ClearField("prior_sigma_um")
    request.sequence = 2
    reply = rpc.call(client, keys.acquire_key("sim"), request, instrument_pb2.AcquireReply)
    assert not reply.header.HasField("prior_z_um")
