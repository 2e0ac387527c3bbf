"""The Zenoh edge: key expressions, the z-stack codec, and request/reply over real sessions."""

from __future__ import annotations

import json
import threading
import time
from typing import ClassVar

import numpy as np
import pytest
import zenoh
from pydantic_settings import SettingsConfigDict

from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc, session


def test_keys_build_and_parse() -> None:
    assert keys.acquire_key("sim") == "focustrack/v1/instrument/sim/acquire"
    assert keys.zstack_key("slide-1", 3, 4) == "focustrack/v1/zstack/slide-1/3/4"
    assert keys.focus_key("s", 0, 9) == "focustrack/v1/focus/s/0/9"
    assert keys.truth_key("sim", "s").startswith("focustrack/v1/eval/")
    assert keys.parse_zstack_key(keys.zstack_key("a.b", 12, 7)) == ("a.b", 12, 7)
    assert keys.parse_focus_key("focustrack/v1/focus/x/1/2") == keys.TileKey("x", 1, 2)
    assert zenoh.KeyExpr(keys.zstack_pattern("x")).intersects(keys.zstack_key("x", 1, 2))
    assert not zenoh.KeyExpr(keys.focus_pattern("x")).intersects(keys.focus_key("y", 1, 2))


@pytest.mark.parametrize(
    ("slides", "matched", "missed"),
    [
        ("*", ["scanner-1-a", "x"], []),
        ("scanner-1-*", ["scanner-1-a", "scanner-1-"], ["scanner-10-a", "x-scanner-1-a"]),
        ("scanner-1-$*", ["scanner-1-a"], ["scanner-2-a"]),  # Zenoh's own spelling
        ("*-b*", ["a-b", "x-bc"], ["ab"]),
        ("slide-0", ["slide-0"], ["slide-01", "slide-1"]),
    ],
)
def test_a_slides_pattern_matches_the_frames_of_its_slides(
    slides: str, matched: list[str], missed: list[str]
) -> None:
    pattern = zenoh.KeyExpr(keys.zframe_pattern(slides))
    assert all(pattern.intersects(keys.zframe_key(slide, 1, 2)) for slide in matched)
    assert not any(pattern.intersects(keys.zframe_key(slide, 1, 2)) for slide in missed)


@pytest.mark.parametrize("slides", ["", "a/b", "a b", "a$", "$x", "**/x"])
def test_bad_slides_patterns_are_refused(slides: str) -> None:
    with pytest.raises(ValueError, match="not a slide name or pattern"):
        keys.zframe_pattern(slides)


@pytest.mark.parametrize("name", ["", "a/b", "*", "a b", "x$"])
def test_bad_names_are_refused(name: str) -> None:
    with pytest.raises(ValueError, match="key chunk"):
        keys.zstack_key(name, 0, 0)


def test_bad_tile_keys_are_refused() -> None:
    with pytest.raises(ValueError):
        keys.zstack_key("s", -1, 0)
    with pytest.raises(ValueError):
        keys.parse_zstack_key("focustrack/v1/focus/s/1/2")
    with pytest.raises(ValueError):
        keys.parse_focus_key("focustrack/v1/focus/s/x/2")


def _stack() -> tuple[instrument_pb2.ZStackHeader, np.ndarray]:
    pixels = np.random.default_rng(0).integers(0, 4096, size=(3, 8, 6, 3), dtype=np.uint16)
    header = instrument_pb2.ZStackHeader(slide="s", row=1, col=2, z_um=[0.0, 0.5, 1.0])
    return header, pixels


def test_codec_round_trips_both_forms() -> None:
    header, pixels = _stack()
    payload, attachment = codec.encode_zstack(header, pixels)
    decoded_header, decoded = codec.decode_zstack(payload, attachment)
    assert decoded_header.dtype == "<u2" and list(decoded_header.shape) == [3, 8, 6, 3]
    np.testing.assert_array_equal(decoded, pixels)
    header_2, pixels_2 = codec.decode_zstack_message(codec.encode_zstack_message(header, pixels))
    assert header_2 == decoded_header
    np.testing.assert_array_equal(pixels_2, pixels)


def test_codec_refuses_inconsistent_stacks() -> None:
    header, pixels = _stack()
    payload, attachment = codec.encode_zstack(header, pixels)
    with pytest.raises(ValueError, match="needs"):
        codec.decode_zstack(payload[:-2], attachment)
    with pytest.raises(ValueError, match="no header"):
        codec.decode_zstack(payload, None)
    with pytest.raises(ValueError, match="z values"):
        codec.encode_zstack(header, pixels[:2])


def test_zstack_travels_between_clients(pair) -> None:
    _, publisher, subscriber = pair
    header, pixels = _stack()
    received: list[tuple[instrument_pb2.ZStackHeader, np.ndarray]] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append(codec.decode_zstack_sample(sample))
        done.set()

    with subscriber.declare_subscriber(keys.zstack_pattern("s"), on_sample):
        payload, attachment = codec.encode_zstack(header, pixels)
        # the subscription needs a moment to reach the publisher through the hub
        for _ in range(50):
            publisher.put(keys.zstack_key("s", 1, 2), payload, attachment=attachment)
            if done.wait(0.1):
                break
    assert received, "no z-stack arrived"
    got_header, got_pixels = received[0]
    assert (got_header.slide, got_header.row, got_header.col) == ("s", 1, 2)
    np.testing.assert_array_equal(got_pixels, pixels)


def test_has_subscribers_says_whether_anyone_listens(pair) -> None:
    _, publisher_session, subscriber_session = pair
    publisher = codec.PixelPublisher(publisher_session)
    key = keys.zstack_key("s", 1, 2)
    assert publisher.has_subscribers(key) is False
    with subscriber_session.declare_subscriber(keys.zstack_pattern("s"), lambda _: None):
        for _ in range(50):  # the subscription needs a moment to reach the publisher
            if publisher.has_subscribers(key):
                break
            time.sleep(0.1)
        assert publisher.has_subscribers(key) is True
        assert publisher.has_subscribers(keys.zstack_key("other", 1, 2)) is False


def test_call_returns_replies_and_raises_error_replies(pair) -> None:
    hub, caller, _ = pair
    key = "focustrack/v1/instrument/test/acquire"

    def handle(query: zenoh.Query) -> instrument_pb2.AcquireReply:
        request = rpc.parse_request(query, instrument_pb2.AcquireRequest)
        if request.n_frames > 3:
            raise rpc.RequestError(
                rpc.ErrorCode.ERROR_CODE_TOO_MANY_FRAMES, "at most 3 frames", "n_frames"
            )
        if request.n_frames == 0:
            raise RuntimeError("boom")
        return instrument_pb2.AcquireReply(header=instrument_pb2.ZStackHeader(slide=request.slide))

    with rpc.declare_answering(hub, key, handle):
        reply = rpc.call(caller, key, instrument_pb2.AcquireRequest(slide="s", n_frames=2),
                         instrument_pb2.AcquireReply)  # fmt: skip
        assert reply.header.slide == "s"
        with pytest.raises(rpc.RemoteError) as refused:
            rpc.call(caller, key, instrument_pb2.AcquireRequest(n_frames=9),
                     instrument_pb2.AcquireReply)  # fmt: skip
        assert refused.value.error.code == common_pb2.ERROR_CODE_TOO_MANY_FRAMES
        assert refused.value.error.field == "n_frames"
        with pytest.raises(rpc.RemoteError, match="boom"):
            rpc.call(caller, key, instrument_pb2.AcquireRequest(), instrument_pb2.AcquireReply)
        garbage = list(caller.get(key, payload=b"\xff\xff\xff", timeout=5.0))
        assert rpc.error_of(garbage[0].err).code == common_pb2.ERROR_CODE_MALFORMED_REQUEST
    with pytest.raises(rpc.RemoteError, match="no queryable"):
        rpc.call(caller, key, instrument_pb2.AcquireRequest(), instrument_pb2.AcquireReply, 0.5)


class _Listener(session.ZenohSettings):
    """A service that listens on the default endpoint, as the instrument does."""

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_WIRE_TEST_")
    default_listen: ClassVar[tuple[str, ...]] = (session.DEFAULT_ENDPOINT,)


def test_session_settings_default_and_override() -> None:
    assert _Listener().endpoints() == ([], [session.DEFAULT_ENDPOINT])
    chosen = _Listener(connect=["tcp/127.0.0.1:1"], mode="client", shared_memory=2)
    assert chosen.endpoints() == (["tcp/127.0.0.1:1"], []) and chosen.shared_memory_bytes == 2e6
    assert json.loads(chosen.zenoh().get_json("mode")) == "client"
    with pytest.raises(ValueError, match="at least one"):
        session.session_config()


@pytest.mark.parametrize(
    ("connect", "listen", "message"),
    [
        ([], ["bogus-endpoint"], "--listen: Endpoints must be of the form"),
        (["tcp/127.0.0.1:99999"], [], "--connect tcp/127.0.0.1:99999: the port must be"),
        ([], ["tcp/[::1]:x"], "--listen tcp/.::1.:x: the port must be"),
        (["udp/127.0.0.1:-1"], [], "the port must be a number"),
    ],
)
def test_an_endpoint_zenoh_cannot_use_is_a_value_error_naming_its_flag(
    connect: list[str], listen: list[str], message: str
) -> None:
    """Zenoh refused a malformed endpoint with its Rust source's path (a traceback in the
    services), and took a port out of range, failing at every attempt after."""
    with pytest.raises(ValueError, match=message) as refused:
        session.session_config(connect, listen)
    assert "/root/.cargo" not in str(refused.value)


def test_ip_endpoints_with_ports_in_range_are_taken() -> None:
    config = session.session_config(["tcp/127.0.0.1:7447", "udp/[::1]:0"], ["tcp/0.0.0.0:65535"])
    assert json.loads(config.get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:7447",
        "udp/[::1]:0",
    ]


def test_pixel_array_is_sent_from_its_own_buffer_and_frames_round_trip() -> None:
    header, pixels = _stack()
    own = codec.pixel_array(pixels.shape, pixels.dtype)
    own[...] = pixels
    payload = codec.raw_payload(own)
    assert isinstance(payload, bytearray)  # the array's own buffer: no copy
    assert np.frombuffer(payload, np.uint8).ctypes.data == own.ctypes.data
    assert isinstance(codec.raw_payload(own[1]), bytes)  # part of a buffer: one copy
    codec.describe_pixels(header, own)
    frame_header = codec.frame_header(header, 2, own[2])
    decoded_header, frame = codec.decode_zframe(
        codec.raw_payload(own[2]), frame_header.SerializeToString()
    )
    assert decoded_header.index == 2 and decoded_header.stack == header
    np.testing.assert_array_equal(frame, pixels[2])
    with pytest.raises(ValueError, match="frame 3 of a stack of 3"):
        codec.frame_header(header, 3, own[2])
    with pytest.raises(ValueError, match="needs"):
        codec.decode_zframe(codec.raw_payload(own[2])[:-2], frame_header.SerializeToString())
    with pytest.raises(ValueError, match="no header"):
        codec.decode_zframe(codec.raw_payload(own[2]), None)


def _frame_parts(
    stack: instrument_pb2.ZStackHeader, index: int, frame: np.ndarray, cuts: list[int], parts: int
) -> list[tuple[instrument_pb2.ZFrameHeader, bytes]]:
    """(header, payload) of each part of `frame` cut at byte offsets `cuts` (0 first),
    each header saying the frame comes in `parts`."""
    data = frame.tobytes()
    pieces = []
    for start, end in zip(cuts, [*cuts[1:], len(data)], strict=True):
        header = codec.frame_header(stack, index, frame)
        header.parts, header.part_offset = parts, start
        pieces.append((header, data[start:end]))
    return pieces


def test_frames_in_parts_are_joined_and_parts_that_do_not_fit_refused() -> None:
    header, pixels = _stack()  # frames of 8 x 6 x 3 uint16: 288 bytes
    codec.describe_pixels(header, pixels)
    assembler = codec.FrameAssembler()
    whole = codec.frame_header(header, 0, pixels[0])
    np.testing.assert_array_equal(assembler.add("k", whole, pixels[0].tobytes()), pixels[0])
    first, second, third = _frame_parts(header, 1, pixels[1], [0, 100, 200], parts=3)
    assert assembler.add("k", *first) is None and assembler.add("k", *second) is None
    np.testing.assert_array_equal(assembler.add("k", *third), pixels[1])
    with pytest.raises(ValueError, match="not a whole frame"):
        codec.decode_zframe(second[1], second[0].SerializeToString())
    # a part lost: the frame is refused, and so are its later parts
    assert assembler.add("k", *first) is None
    with pytest.raises(ValueError, match="at byte 200, expected 100: a part was lost"):
        assembler.add("k", *third)
    with pytest.raises(ValueError, match="expected 0"):
        assembler.add("k", *second)
    # a first part starts the frame over
    assert assembler.add("k", *first) is None and assembler.add("k", *first) is None
    assert assembler.add("k", *second) is None
    np.testing.assert_array_equal(assembler.add("k", *third), pixels[1])
    # the last part (by count) must end the frame, and no part may end past it
    short_first, short_last = _frame_parts(header, 1, pixels[1], [0, 100], parts=3)[:2]
    assert assembler.add("k", *short_first) is None
    with pytest.raises(ValueError, match="part 2 of 3 of frame 1 ends at byte 288 of 288"):
        assembler.add("k", *short_last)
    first, last = _frame_parts(header, 1, pixels[1], [0, 100], parts=2)
    assert assembler.add("k", *first) is None
    with pytest.raises(ValueError, match="ends at byte 290 of 288"):
        assembler.add("k", last[0], last[1] + b"xx")
    # frames on two keys are joined side by side
    assert assembler.add("k", *first) is None
    assert assembler.add("other", *first) is None
    np.testing.assert_array_equal(assembler.add("k", *last), pixels[1])
    np.testing.assert_array_equal(assembler.add("other", *last), pixels[1])
    assert assembler.open_bytes == 0


class _Clock:
    """A clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_frames_under_way_are_bounded_in_bytes_and_refused_before_their_buffer() -> None:
    header, pixels = _stack()  # frames of 288 bytes
    codec.describe_pixels(header, pixels)
    held = [0]
    assembler = codec.FrameAssembler(budget_bytes=700, held_elsewhere=lambda: held[0])
    first, last = _frame_parts(header, 1, pixels[1], [0, 100], parts=2)
    assert assembler.add("a", *first) is None and assembler.add("b", *first) is None
    assert assembler.open_bytes == 2 * 288  # whole buffers, though 100 bytes came of each
    with pytest.raises(ValueError, match="frame of 288 bytes does not fit in the 124 bytes"):
        assembler.add("c", *first)
    assert assembler.n_refused == 1 and assembler.open_bytes == 2 * 288  # nothing taken
    with pytest.raises(ValueError, match="expected 0"):  # nor its later parts
        assembler.add("c", *last)
    np.testing.assert_array_equal(assembler.add("a", *last), pixels[1])
    assert assembler.open_bytes == 288  # a frame done is off the count
    held[0] = 200  # what the owner holds shares the budget
    with pytest.raises(ValueError, match="does not fit"):
        assembler.add("c", *first)
    held[0] = 0
    assert assembler.add("c", *first) is None
    # a declared gigabyte is refused before its buffer is taken
    huge = instrument_pb2.ZFrameHeader()
    huge.CopyFrom(first[0])
    huge.stack.shape[1:] = [16384, 16384, 4]
    with pytest.raises(ValueError, match="frame of 2147483648 bytes does not fit"):
        assembler.add("d", huge, first[1])
    assert assembler.open_bytes == 2 * 288
    # a whole frame is the caller's to keep: nothing taken here
    whole = codec.frame_header(header, 0, pixels[0])
    np.testing.assert_array_equal(assembler.add("e", whole, pixels[0].tobytes()), pixels[0])


def test_frames_whose_parts_stop_coming_expire() -> None:
    header, pixels = _stack()
    codec.describe_pixels(header, pixels)
    clock = _Clock()
    assembler = codec.FrameAssembler(timeout_s=10.0, clock=clock)
    first, second, third = _frame_parts(header, 1, pixels[1], [0, 100, 200], parts=3)
    assert assembler.add("a", *first) is None
    clock.now_s = 6.0
    assert assembler.add("b", *first) is None
    clock.now_s = 9.0
    assert assembler.add("a", *second) is None  # a part came: "a" waits 10 s from now
    clock.now_s = 16.5
    assert assembler.expire() == 1 and assembler.open_bytes == 288  # "b": 10.5 s without
    assert assembler.n_expired == 1
    np.testing.assert_array_equal(assembler.add("a", *third), pixels[1])
    with pytest.raises(ValueError, match="expected 0: a part was lost"):
        assembler.add("b", *second)
    assert assembler.add("c", *first) is None
    clock.now_s = 30.0
    assert assembler.expire() == 1 and assembler.open_bytes == 0
    with pytest.raises(ValueError, match="must be positive"):
        codec.FrameAssembler(timeout_s=0)


@pytest.mark.parametrize("part_bytes", [0, 100, 288])
def test_a_publisher_sends_frames_in_parts_that_a_subscriber_joins(pair, part_bytes: int) -> None:
    _, publisher_session, subscriber_session = pair
    header, pixels = _stack()  # frames of 288 bytes
    codec.describe_pixels(header, pixels)
    publisher = codec.PixelPublisher(publisher_session, part_bytes=part_bytes)
    assembler = codec.FrameAssembler()
    samples: list[int] = []  # each sample's part_offset
    frames: list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        samples.append(codec.zframe_header(sample.attachment.to_bytes()).part_offset)
        if (frame := assembler.add_sample(sample)) is not None:
            frames.append(frame)

    key = keys.zframe_key("s", 1, 2)
    with subscriber_session.declare_subscriber(keys.zframe_pattern("s"), on_sample):
        for _ in range(50):  # the subscription needs a moment to reach the publisher
            if publisher.has_subscribers(key):
                break
            time.sleep(0.1)
        for index in range(3):
            publisher.put_frame(key, header, index, pixels[index])
        for _ in range(50):
            if len(frames) == 3:
                break
            time.sleep(0.1)
    assert samples == ([0, 100, 200] if part_bytes == 100 else [0]) * 3
    assert [frame_header.index for frame_header, _ in frames] == [0, 1, 2]
    for (_, frame), expected in zip(frames, pixels, strict=True):
        np.testing.assert_array_equal(frame, expected)  # a reused part buffer corrupts none
    with pytest.raises(ValueError, match="0 sends frames whole"):
        codec.PixelPublisher(publisher_session, part_bytes=-1)


@pytest.mark.parametrize("shared_memory", [True, False])
def test_frames_travel_through_shared_memory_or_fall_back_to_the_network(
    shared_memory: bool,
) -> None:
    """A publisher with a shared-memory pool reaches a subscriber that accepts shared
    memory through it, and one that has it off over the network, with the same pixels."""
    endpoint = session.loopback_endpoint()
    header, pixels = _stack()
    codec.describe_pixels(header, pixels)
    received: list[tuple[bool, instrument_pb2.ZFrameHeader, np.ndarray]] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        frame_header, frame = codec.decode_zframe_sample(sample)
        received.append((sample.payload.as_shm() is not None, frame_header, frame))
        done.set()

    with (
        session.open_session(listen=[endpoint], shared_memory=True) as hub,
        session.open_session(connect=[endpoint], shared_memory=shared_memory) as listener,
        listener.declare_subscriber(keys.zframe_pattern("s"), on_sample),
    ):
        publisher = codec.PixelPublisher(hub, shm_pool_bytes=1 << 20)
        too_small = codec.PixelPublisher(hub, shm_pool_bytes=4096)
        large = np.zeros((64, 64, 3), np.uint16)
        assert isinstance(too_small.payload(large), bytes) and too_small.n_network == 1
        for _ in range(50):  # the subscription needs a moment to reach the publisher
            publisher.put_frame(keys.zframe_key("s", 1, 2), header, 1, pixels[1])
            if done.wait(0.1):
                break
    assert received, "no frame arrived"
    through_shm, frame_header, frame = received[0]
    assert publisher.n_shared >= 1 and publisher.n_network == 0
    assert through_shm is shared_memory
    assert frame_header.index == 1 and frame_header.stack.row == 1
    np.testing.assert_array_equal(frame, pixels[1])


def test_a_wait_for_the_bus_is_said_once_after_its_patience() -> None:
    """`open_config` calls `on_wait` once while Zenoh still waits for its endpoint (the scan
    used to wait 30 s for a missing router in silence), and not at all for a quick open."""
    said: list[str] = []
    nowhere = session.session_config(connect=[session.loopback_endpoint()], connect_timeout_s=1.0)
    with pytest.raises(zenoh.ZError):
        session.open_config(nowhere, lambda: said.append("waiting"), patience_s=0.2)
    assert said == ["waiting"]
    alone = session.session_config(listen=[session.loopback_endpoint()])
    with session.open_config(alone, lambda: said.append("again"), patience_s=0.2):
        pass
    assert said == ["waiting"]
