"""`focustrack-instrument-sim` over real Zenoh on loopback: stacks, metadata, truth, errors,
and every frame and stack tagged with its frame key."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
import zenoh
from instrument_process import wait_until_it_answers

from focustrack_core import health
from focustrack_core.geometry import MAX_TILES
from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc, session
from focustrack_core.wire.trust import NONCE_BYTES, FrameSigner
from focustrack_instrument_sim import service

SIZE = 128
FRAME_KEY = "5a" * 32  # the instrument's frame key (hex digits: 64 bytes of key)
SIGNER = FrameSigner(FRAME_KEY.encode())


def _tag_checks(sample: zenoh.Sample, header: instrument_pb2.ZFrameHeader) -> bool:
    """True when the sample carries the frame key's tag of it."""
    assert sample.attachment is not None
    payload = codec.payload_bytes(sample.payload)
    return SIGNER.verify(str(sample.key_expr), header, sample.attachment.to_bytes(), payload)


#: The port of the instrument's metrics (`--metrics-port`).
METRICS_PORT = session.free_port()


@pytest.fixture(scope="module")
def instrument(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The service in its own process, listening on a free port; yields the endpoint."""
    endpoint = session.loopback_endpoint()
    key_file = tmp_path_factory.mktemp("keys") / "frame.key"
    key_file.write_text(FRAME_KEY + "\n")
    command = [
        sys.executable, "-m", "focustrack_instrument_sim", "--listen", endpoint,
        "--name", "sim", "--seed", "3", "--slides", "2", "--rows", "4", "--cols", "5",
        "--width", str(SIZE), "--height", str(SIZE), "--max-frames", "25", "--serve-truth",
        "--frame-part-kb", "32",  # frames of 96 KiB go in 3 parts
        "--frame-key-file", str(key_file), "--metrics-port", str(METRICS_PORT),
    ]  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    try:
        with session.open_session(connect=[endpoint], connect_timeout_s=60) as probe:
            wait_until_it_answers(probe, "sim", process)
        yield endpoint
    finally:
        process.terminate()
        assert process.wait(timeout=20) == 0


@pytest.fixture
def client(instrument: str) -> Iterator[zenoh.Session]:
    with session.open_session(connect=[instrument]) as opened:
        yield opened


def _request(**fields) -> instrument_pb2.AcquireRequest:
    defaults = dict(slide="slide-0", row=1, col=2, z_low_um=-2.0, z_step_um=0.5, n_frames=9)
    return instrument_pb2.AcquireRequest(**{**defaults, **fields})


def test_info_describes_slides_and_optics(client: zenoh.Session) -> None:
    info = rpc.call(client, keys.info_key("sim"), instrument_pb2.AcquireRequest(),
                    instrument_pb2.InstrumentInfo)  # fmt: skip
    assert [s.slide for s in info.slides] == ["slide-0", "slide-1"]
    assert (info.slides[0].rows, info.slides[0].cols) == (4, 5)
    assert info.width == SIZE and info.max_frames == 25 and info.channel_order == "RGB"
    assert 0.7 < info.depth_of_field_um < 1.1
    assert info.HasField("laser") and not info.laser  # said, so a laser scan is refused at once


def test_acquire_publishes_frames_and_the_stack_and_replies_with_timing(
    client: zenoh.Session,
) -> None:
    received: list[tuple[instrument_pb2.ZStackHeader, np.ndarray]] = []
    frames: list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]] = []
    tags_checked: list[bool] = []  # of every sample: frame parts, then the stack
    arrived = threading.Event()

    def on_stack(sample: zenoh.Sample) -> None:
        received.append(codec.decode_zstack_sample(sample))
        tags_checked.append(_tag_checks(sample, received[-1][0]))  # type: ignore[arg-type]
        arrived.set()

    assembler = codec.FrameAssembler()

    def on_frame(sample: zenoh.Sample) -> None:
        assert sample.attachment is not None
        tags_checked.append(_tag_checks(sample, codec.zframe_header(sample.attachment.to_bytes())))
        if (frame := assembler.add_sample(sample)) is not None:
            frames.append(frame)

    with (
        client.declare_subscriber(keys.zstack_pattern("slide-0"), on_stack),
        client.declare_subscriber(keys.zframe_pattern("slide-0"), on_frame),
    ):
        time.sleep(0.5)  # let the subscriptions reach the instrument
        reply = rpc.call(client, keys.acquire_key("sim"), _request(sequence=42, nonce=b"n" * 16),
                         instrument_pb2.AcquireReply)  # fmt: skip
        assert arrived.wait(10), "the stack was not published"
        for _ in range(100):  # frames and stack may be handed over on different threads
            if len(frames) == 9:
                break
            time.sleep(0.1)
    header, pixels = received[0]
    # every frame came first, one by one, in order, with the stack's pixels
    assert [frame_header.index for frame_header, _ in frames] == list(range(9))
    for frame_header, frame in frames:
        assert frame_header.stack.sequence == 42 and frame_header.timestamp_unix_s > 0
        assert frame_header.parts == 3  # --frame-part-kb 32
        np.testing.assert_array_equal(frame, pixels[frame_header.index])
    assert pixels.shape == (9, SIZE, SIZE, 3) and pixels.dtype == np.uint16
    assert (header.slide, header.row, header.col, header.sequence) == ("slide-0", 1, 2, 42)
    np.testing.assert_allclose(header.z_um, -2.0 + 0.5 * np.arange(9))
    assert header.channel_order == "RGB" and pixels.max() < 2**header.bit_depth
    assert header.stage_x_um == 400.0 and header.stage_y_um == 200.0
    # the acquisition's nonce is in every header; each sample carries its frame tag
    assert header.nonce == b"n" * 16 and header.tag and not reply.header.tag
    assert all(frame_header.stack.nonce == b"n" * 16 for frame_header, _ in frames)
    assert tags_checked == [True] * (9 * 3 + 1)
    header.ClearField("tag")  # the stack sample's alone
    assert reply.header == header
    timing = reply.timing
    assert timing.move_distance_um > 0 and timing.move_s > 0
    assert timing.total_s == pytest.approx(
        timing.move_s + timing.z_settle_s + timing.exposure_s + timing.readout_s
    )
    assert timing.clock_s >= timing.total_s


@pytest.mark.parametrize(
    "option",
    [
        ["--frame-part-kb", "-1"],
        ["--keep-frames-mb", "-1"],
        ["--queue-depth", "0"],
        ["--shared-memory", "-1"],
        ["--workers", "0"],
        ["--rows", "0"],
        ["--cols", "1001"],
        ["--name", "a/b"],  # not one key chunk: a traceback once the bus was open
        ["--map", "/no/such/map.npy"],  # a traceback once the options were taken
        ["--width", "100000"],  # 10^10 pixels a frame, taken
        ["--pitch-um", "inf"],  # no option means infinity or NaN
        ["--z-offset-um", "nan"],
    ],
)
def test_a_refused_option_ends_the_command_naming_it(
    option: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as refused:
        service.main(["--connect", session.loopback_endpoint(), "--rows", "2", *option])
    assert refused.value.code == 2
    variable = service.Settings.variable(option[0][2:].replace("-", "_"))
    assert f"{option[0]} ({variable}):" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--width", "33"], "frame sides must be even"),
        (["--na", "1.2"], "NA must lie in (0, n=1.0)"),
    ],
)
def test_a_value_the_simulator_refuses_ends_the_command_before_it_serves(
    option: list[str], message: str, caplog: pytest.LogCaptureFixture
) -> None:
    assert service.main(["--connect", session.loopback_endpoint(), *option]) == 2
    assert message in caplog.text


def test_a_metrics_port_in_use_ends_the_command_before_the_instrument_is_seen(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        listen = ["--mode", "peer", "--listen", session.loopback_endpoint()]
        argv = [*listen, "--rows", "2", "--cols", "2", "--metrics-port", str(port)]
        assert service.main(argv) == 2
    assert f"the metrics server cannot listen on 127.0.0.1:{port}" in caplog.text


def test_a_grid_beyond_the_estimators_tiles_ends_the_command_before_a_surface_is_drawn(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """1000 x 1000 tiles: each side allowed, their product not (it is the estimator's
    limit). A grid of 10^10 tiles used to end in a MemoryError from the surface generator."""
    with pytest.raises(SystemExit) as refused:
        service.main(["--connect", session.loopback_endpoint(), "--rows", "1000", "--cols", "1000"])
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert f"error: grid 1000x1000 is too large: at most 1000 tiles a side and {MAX_TILES}" in err
    assert "Traceback" not in err and "FOCUSTRACK_INSTRUMENT_)" not in err  # no flag of its own


#: Every option of `focustrack serve instrument`: the users' contract (added to, never renamed).
OPTIONS = [
    "connect", "listen", "mode", "zenoh-config", "shared-memory", "name", "backend", "seed",
    "slides", "rows", "cols", "family", "map", "pitch-um", "z-offset-um", "width", "height",
    "max-frames", "workers", "cache-mb", "na", "magnification", "drift-um-per-s",
    "dust-density", "realtime", "keep-frames-mb", "frame-part-kb", "queue-depth", "serve-truth",
    "specimen", "condenser-na", "drift-settle-um", "drift-settle-tau-s",
    "drift-walk-um-per-sqrt-min", "laser", "laser-noise-um", "laser-offset-um",
    "laser-offset-sigma-um",
]  # fmt: skip


def test_help_lists_every_option_and_its_variable(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as helped:
        service.main(["--help"])
    assert helped.value.code == 0
    text = capsys.readouterr().out
    for option in OPTIONS:
        assert re.search(rf"--{option}[ ,\n]", text), option
        assert f"[env FOCUSTRACK_INSTRUMENT_{option.replace('-', '_').upper()}]" in " ".join(
            text.split()
        )


def test_the_health_probe_passes_for_this_instrument_and_fails_for_another(
    instrument: str, capsys: pytest.CaptureFixture[str]
) -> None:
    probe = ["--connect", instrument, "--timeout-s", "5", "--instrument"]
    assert health.main([*probe, "sim"]) == 0
    assert health.main([*probe[:3], "1", "--instrument", "nobody"]) == 1
    assert "unhealthy: TimeoutError: instrument 'nobody' did not answer" in capsys.readouterr().err


def test_truth_is_apart_and_matches_the_slide(client: zenoh.Session) -> None:
    truth = rpc.call(client, keys.truth_key("sim", "slide-1"), instrument_pb2.AcquireRequest(),
                     instrument_pb2.SlideTruth)  # fmt: skip
    assert (truth.rows, truth.cols, len(truth.best_focus_um)) == (4, 5, 20)
    assert keys.truth_key("sim", "slide-1").startswith("focustrack/v1/eval/")
    with pytest.raises(rpc.RemoteError) as refused:
        rpc.call(client, keys.truth_key("sim", "nope"), instrument_pb2.AcquireRequest(),
                 instrument_pb2.SlideTruth)  # fmt: skip
    assert refused.value.error.code == common_pb2.ERROR_CODE_UNKNOWN_SLIDE


@pytest.mark.parametrize(
    ("fields", "code", "field"),
    [
        ({"slide": "nope"}, common_pb2.ERROR_CODE_UNKNOWN_SLIDE, "slide"),
        ({"row": 4}, common_pb2.ERROR_CODE_TILE_OUTSIDE_SLIDE, "row"),
        ({"col": -1}, common_pb2.ERROR_CODE_TILE_OUTSIDE_SLIDE, "col"),
        ({"z_low_um": 99.0}, common_pb2.ERROR_CODE_Z_OUT_OF_RANGE, "z_low_um"),
        ({"n_frames": 26}, common_pb2.ERROR_CODE_TOO_MANY_FRAMES, "n_frames"),
        ({"n_frames": 0}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "n_frames"),
        ({"z_step_um": 0.0}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "z_step_um"),
        ({"z_step_um": 1e-7}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "z_step_um"),
        # predictions the focus service refuses: they cost a whole stack, then an error
        ({"prior_z_um": float("nan")}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "prior_z_um"),
        ({"prior_sigma_um": 0.0}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "prior_sigma_um"),
        ({"prior_sigma_um": -1.0}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "prior_sigma_um"),
        ({"nonce": b"n" * 65}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "nonce"),
    ],
)
def test_bad_requests_get_error_replies(client: zenoh.Session, fields, code, field) -> None:
    with pytest.raises(rpc.RemoteError) as refused:
        rpc.call(client, keys.acquire_key("sim"), _request(**fields), instrument_pb2.AcquireReply)
    assert refused.value.error.code == code
    assert refused.value.error.field == field
    assert refused.value.error.message


def test_a_request_without_a_nonce_gets_a_fresh_one(client: zenoh.Session) -> None:
    request, reply_type = _request(n_frames=1), instrument_pb2.AcquireReply
    nonces = {rpc.call(client, keys.acquire_key("sim"), request, reply_type).header.nonce
              for _ in range(2)}  # fmt: skip
    assert len(nonces) == 2 and all(len(nonce) == NONCE_BYTES for nonce in nonces)


def test_malformed_message_gets_an_error_and_the_service_keeps_running(client) -> None:
    replies = list(client.get(keys.acquire_key("sim"), payload=b"\x08\xff\xff", timeout=10))
    assert rpc.error_of(replies[0].err).code == common_pb2.ERROR_CODE_MALFORMED_REQUEST
    reply = rpc.call(client, keys.acquire_key("sim"), _request(n_frames=1),
                     instrument_pb2.AcquireReply)  # fmt: skip
    assert len(reply.header.z_um) == 1


def _frames_query(
    client: zenoh.Session, **fields
) -> list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]]:
    """The frames replied to a FramesRequest; RemoteError on an error reply."""
    request = instrument_pb2.FramesRequest(**{"slide": "slide-0", "row": 3, "col": 4, **fields})
    replies = client.get(
        keys.frames_key("sim"),
        payload=request.SerializeToString(),
        timeout=10,
        consolidation=zenoh.ConsolidationMode.NONE,  # every frame replies on the same key
    )
    frames = []
    for reply in replies:
        if reply.err is not None:
            raise rpc.RemoteError(rpc.error_of(reply.err))
        frames.append(codec.decode_zframe_sample(reply.ok))
        assert _tag_checks(reply.ok, frames[-1][0])  # tagged as published, on the query's key
    return frames


def test_the_frames_of_a_recent_stack_are_answered_as_they_were_published(
    client: zenoh.Session,
) -> None:
    published: list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]] = []
    assembler = codec.FrameAssembler()

    def on_frame(sample: zenoh.Sample) -> None:
        if (frame := assembler.add_sample(sample)) is not None:
            published.append(frame)

    with client.declare_subscriber(keys.zframe_pattern("slide-0"), on_frame):
        time.sleep(0.5)  # let the subscription reach the instrument
        rpc.call(client, keys.acquire_key("sim"), _request(row=3, col=4, sequence=77, n_frames=5),
                 instrument_pb2.AcquireReply)  # fmt: skip
        for _ in range(100):
            if len(published) == 5:
                break
            time.sleep(0.1)
    by_index = {header.index: frame for header, frame in published if header.stack.sequence == 77}
    answered = _frames_query(client, sequence=77, indices=[4, 0])
    assert [header.index for header, _ in answered] == [4, 0]
    for header, frame in answered:
        assert (header.stack.row, header.stack.col, header.stack.sequence) == (3, 4, 77)
        np.testing.assert_array_equal(frame, by_index[header.index])
    assert [header.index for header, _ in _frames_query(client, sequence=77)] == list(range(5))
    # a frame named 2,000 times (a 2 KB request) is sent once: not 2,000 copies of 96 KiB
    request_bytes = instrument_pb2.FramesRequest(sequence=77, indices=[3] * 2000).ByteSize()
    assert request_bytes < 2100
    [(header, frame)] = _frames_query(client, sequence=77, indices=[3] * 2000)
    assert header.index == 3
    np.testing.assert_array_equal(frame, by_index[3])
    repeated = _frames_query(client, sequence=77, indices=[2, 2, 0, 2])
    assert [header.index for header, _ in repeated] == [2, 0]

    with pytest.raises(rpc.RemoteError) as gone:
        _frames_query(client, sequence=78)  # never taken
    assert gone.value.error.code == common_pb2.ERROR_CODE_FRAMES_GONE
    assert "is not held" in gone.value.error.message
    with pytest.raises(rpc.RemoteError) as outside:
        _frames_query(client, sequence=77, indices=[5])
    assert outside.value.error.code == common_pb2.ERROR_CODE_MALFORMED_REQUEST
    assert outside.value.error.field == "indices"
    replies = list(client.get(keys.frames_key("sim"), payload=b"\x08\xff\xff", timeout=10))
    assert rpc.error_of(replies[0].err).code == common_pb2.ERROR_CODE_MALFORMED_REQUEST


def _metrics(http: httpx.Client) -> dict[str, float]:
    """The instrument's metrics now, by sample (name and labels)."""
    text = http.get(f"http://127.0.0.1:{METRICS_PORT}/metrics").text
    return {
        sample: float(value)
        for sample, value in (line.rsplit(" ", 1) for line in text.splitlines() if line[0] != "#")
    }


def test_the_metrics_port_counts_stacks_frames_and_errors_by_code(
    http: httpx.Client, client: zenoh.Session
) -> None:
    before = _metrics(http)
    rpc.call(client, keys.acquire_key("sim"), _request(n_frames=7), instrument_pb2.AcquireReply)
    with pytest.raises(rpc.RemoteError):
        rpc.call(client, keys.acquire_key("sim"), _request(row=4), instrument_pb2.AcquireReply)
    after = _metrics(http)
    grown = {sample: after[sample] - before.get(sample, 0.0) for sample in after}
    assert grown["focustrack_instrument_acquisitions_total"] == 1
    assert grown["focustrack_instrument_frames_total"] == 7
    refused = 'focustrack_instrument_errors_total{code="ERROR_CODE_TILE_OUTSIDE_SLIDE"}'
    assert grown[refused] == 1
    assert grown["focustrack_instrument_acquisition_duration_seconds_count"] == 2
    assert after["focustrack_instrument_busy_total"] == 0
    assert after["focustrack_instrument_queued"] == 0


def test_a_wildcard_query_is_one_acquisition_on_an_instrument_with_a_laser() -> None:
    """A query for probe/* reaches the acquisition's queryable and the laser's: each used to
    read its key expression, not its queryable, and both acquired (6 frames for 3)."""
    endpoint = session.loopback_endpoint()
    command = [
        sys.executable, "-m", "focustrack_instrument_sim", "--listen", endpoint, "--name",
        "probe", "--rows", "2", "--cols", "2", "--width", "64", "--height", "64", "--laser",
    ]  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    try:
        with session.open_session(connect=[endpoint], connect_timeout_s=60) as client:
            wait_until_it_answers(client, "probe", process)
            info = rpc.call(client, keys.info_key("probe"), instrument_pb2.AcquireRequest(),
                            instrument_pb2.InstrumentInfo)  # fmt: skip
            assert info.laser
            frames: list[zenoh.Sample] = []
            with client.declare_subscriber(keys.zframe_pattern("slide-0"), frames.append):
                time.sleep(0.5)  # let the subscription reach the instrument
                request = _request(row=0, col=0, n_frames=3, nonce=b"w" * 16)
                replies = list(
                    client.get(
                        "focustrack/v1/instrument/probe/*",
                        payload=request.SerializeToString(),
                        timeout=20,
                    )
                )
                time.sleep(0.5)  # the frames' samples after the replies
            headers = [codec.zframe_header(s.attachment.to_bytes()) for s in frames]  # type: ignore[union-attr]
            assert len(replies) >= 1
            # one stack of 3 frames (of one part each), not two
            assert sorted((h.index, h.part_offset) for h in headers) == [(0, 0), (1, 0), (2, 0)]
    finally:
        process.terminate()
        assert process.wait(timeout=20) == 0
