"""The phase service on real Zenoh (loopback): the frames of a phase stack, published as the
instrument publishes them (tagged, in parts), come back as a PhaseResult whose phase is the
specimen's; focus stacks are not its business; a stack it cannot read gets an error result."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from focustrack_core.testing import within
from focustrack_core.v1 import common_pb2, instrument_pb2, phase_pb2
from focustrack_core.wire import codec, keys
from focustrack_core.wire.codec import PixelPublisher, describe_stack
from focustrack_core.wire.session import AliveTokens, free_port, loopback_endpoint, open_session
from focustrack_core.wire.trust import FrameSigner, ResultSigner
from focustrack_phase.acekf import AcekfOptions
from focustrack_phase.app import PhaseLimits
from focustrack_phase.bus import (
    PhaseOptics,
    PhaseStack,
    PhaseStacks,
    ZenohPhaseWorker,
    phase_input,
)
from focustrack_phase.simulate import through_focus_stack, weak_object

WAVELENGTH_UM = 0.532
PIXEL_UM = 1.0
REFERENCE_Z_UM = 12.0  # the objective z the stack is centred on
OFFSETS_UM = np.arange(-50.0, 50.1, 5.0)  # 21 planes either side of it
GAMMA_PHOTONS = 10_000.0
PHOTONS_PER_COUNT = 2.0
DARK_COUNTS = 100.0
SIZE_PX = 64
PART_BYTES = 3000  # frames of 64 x 64 uint16 go in 3 parts
FRAME_KEY = b"f" * 32
RESULT_KEY = b"r" * 32
PHASE = instrument_pb2.ACQUISITION_PURPOSE_PHASE


def header_of(
    sequence: int, z_um: np.ndarray, purpose: instrument_pb2.AcquisitionPurpose = PHASE
) -> instrument_pb2.ZStackHeader:
    """The header an instrument publishes with a phase stack of tile (1, 2) of slide s1."""
    return instrument_pb2.ZStackHeader(
        instrument="sim",
        slide="s1",
        row=1,
        col=2,
        sequence=sequence,
        z_um=list(z_um),
        pixel_size_um=PIXEL_UM,
        channel_order="L",
        bit_depth=16,
        nonce=bytes([sequence]) * 16,
        purpose=purpose,
        reference_z_um=REFERENCE_Z_UM,
        wavelength_um=WAVELENGTH_UM,
        objective_na=0.85,
        photons_per_count=PHOTONS_PER_COUNT,
        dark_counts=DARK_COUNTS,
    )


def publish(
    publisher: PixelPublisher, header: instrument_pb2.ZStackHeader, counts: np.ndarray
) -> None:
    """Publish every frame of `counts` (n, h, w) as the instrument does."""
    pixels = np.ascontiguousarray(counts[..., None])
    describe_stack(header, pixels.shape, pixels.dtype)
    for index, frame in enumerate(pixels):
        publisher.put_frame(keys.zframe_key("s1", 1, 2), header, index, frame)


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[tuple[PixelPublisher, ZenohPhaseWorker, queue.Queue]]:
    """The instrument's side (a tagging publisher), the phase service's worker, and the
    phase results it publishes as (key, PhaseResult, attachment, payload)."""
    endpoint = loopback_endpoint()
    instrument = open_session(listen=[endpoint])
    service = open_session(connect=[endpoint])
    stacks = PhaseStacks(PhaseLimits(), frame_signer=FrameSigner(FRAME_KEY))
    worker = ZenohPhaseWorker(service, stacks, PhaseOptics(), signer=ResultSigner(RESULT_KEY))
    results: queue.Queue = queue.Queue()

    def on_result(sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        results.put(
            (
                str(sample.key_expr),
                phase_pb2.PhaseResult.FromString(attachment),
                attachment,
                sample.payload.to_bytes(),
            )
        )

    subscriber = instrument.declare_subscriber(keys.phase_pattern("s1"), on_result)
    time.sleep(0.5)  # let the subscriptions reach each other
    publisher = PixelPublisher(instrument, part_bytes=PART_BYTES, signer=FrameSigner(FRAME_KEY))
    yield publisher, worker, results
    subscriber.undeclare()
    worker.close()
    service.close()
    instrument.close()


def camera_counts(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A weak object's true phase (rad, (h, w)) and its through-focus stack as a camera with
    `PHOTONS_PER_COUNT` and `DARK_COUNTS` counts it, uint16 (n, h, w)."""
    field = weak_object(SIZE_PX, seed)
    photons = through_focus_stack(field, OFFSETS_UM, WAVELENGTH_UM, PIXEL_UM, GAMMA_PHOTONS, seed)
    counts = np.rint(photons / PHOTONS_PER_COUNT + DARK_COUNTS).astype(np.uint16)
    return np.angle(field), counts


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef((a - a.mean()).ravel(), (b - b.mean()).ravel())[0, 1])


def test_a_phase_stack_on_the_bus_comes_back_as_its_phase_tagged(bus) -> None:
    publisher, _, results = bus
    truth_rad, counts = camera_counts(seed=4)
    publish(publisher, header_of(7, REFERENCE_Z_UM + OFFSETS_UM), counts)
    key, result, attachment, payload = results.get(timeout=30)
    assert key == keys.phase_key("s1", 1, 2)
    assert (result.slide, result.row, result.col, result.sequence) == ("s1", 1, 2, 7)
    assert result.instrument == "sim" and result.nonce == bytes([7]) * 16
    assert result.reference_z_um == REFERENCE_Z_UM and result.pixel_size_um == PIXEL_UM
    assert not result.HasField("error") and result.compute_time_s > 0
    assert list(result.shape) == [2, SIZE_PX, SIZE_PX] and result.dtype == "<f4"
    assert ResultSigner(RESULT_KEY).verify_attachment(key, result, attachment, payload)
    assert not ResultSigner(b"x" * 32).verify_attachment(key, result, attachment, payload)
    phase_rad, amplitude = codec.phase_field(result, payload)
    assert correlation(phase_rad, truth_rad) > 0.8  # the heights, gain and offset were read
    assert np.mean(amplitude) == pytest.approx(1.0, abs=0.05)  # relative to the stack's mean
    # Anchored to the smear's glass: its share is said (measured 0.47 of the 0.73 that is
    # glass), and there the phase is zero.
    assert 0.25 < result.background_share <= float(np.mean(truth_rad == 0))
    assert abs(float(np.mean(phase_rad[truth_rad == 0]))) < 0.1


def test_focus_stacks_are_ignored_and_a_bad_phase_stack_gets_an_error(bus) -> None:
    publisher, worker, results = bus
    _, counts = camera_counts(seed=5)
    z_um = REFERENCE_Z_UM + OFFSETS_UM
    publish(publisher, header_of(1, z_um, instrument_pb2.ACQUISITION_PURPOSE_FOCUS), counts)
    publish(publisher, header_of(2, z_um[:1]), counts[:1])  # one frame: no phase from it
    untagged = PixelPublisher(publisher.session, part_bytes=PART_BYTES)
    publish(untagged, header_of(3, z_um), counts)  # not the instrument's: dropped
    publish(publisher, header_of(4, z_um), counts)
    # one worker takes the frames in order: the focus stack's came first and got nothing
    _, refused, _, payload = results.get(timeout=30)
    assert refused.sequence == 2 and payload == b""
    assert refused.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert "at least 2 frames" in refused.error.message
    _, result, _, _ = results.get(timeout=30)
    assert result.sequence == 4 and not result.HasField("error")
    assert worker.stacks.n_not_phase == len(z_um) * 3  # every part of every frame
    assert worker.stacks.n_untagged == len(z_um) * 3


def test_the_worker_holds_a_liveliness_token_for_every_slide_until_it_closes() -> None:
    """A scan watches the phase services of its slide (`session.AliveTokens`): the worker's
    token is there once it reads frames, matches any slide, and goes when it closes."""
    endpoint = loopback_endpoint()
    with open_session(listen=[endpoint]) as scheduler, open_session(connect=[endpoint]) as service:
        watched = [AliveTokens(scheduler, keys.alive_pattern("phase", slide)) for slide in "ab"]
        worker = ZenohPhaseWorker(service, PhaseStacks(PhaseLimits()))
        try:
            token = keys.alive_key("phase", "*", str(service.info.zid()))
            assert within(lambda: all(tokens.alive() for tokens in watched))
            assert [tokens.alive() for tokens in watched] == [{token}, {token}]
            focus_services = AliveTokens(scheduler, keys.alive_pattern("focus", "a"))
            assert not focus_services.alive()
            focus_services.close()
            worker.close()
            # gone with the worker, before its session
            assert within(lambda: not any(tokens.alive() for tokens in watched))
        finally:
            worker.close()  # (again, where the test did not get that far)
            for tokens in watched:
                tokens.close()


def test_a_header_without_wavelength_or_gain_takes_the_service_defaults() -> None:
    header = header_of(1, np.array([11.0, 13.0]))
    header.wavelength_um = header.photons_per_count = 0.0
    counts = np.full((2, 4, 4), 150.0, np.float32)
    options = AcekfOptions(condenser_na=0.2)
    given = phase_input(header, counts, PhaseOptics(0.6), options)
    assert given.wavelength_um == 0.6 and given.photons_per_count == 1.0
    assert given.z_um.tolist() == [-1.0, 1.0] and np.all(given.counts == 50.0)
    assert given.options == options  # the header states no condenser NA
    header.condenser_na = 0.35  # partially coherent light: the filter is told
    assert phase_input(header, counts, PhaseOptics(), options).options.condenser_na == 0.35
    for bad_na in (np.nan, -1.0):  # taken as coherent light, where REST refuses them
        header.condenser_na = bad_na
        with pytest.raises(ValueError, match="gives a condenser NA of"):
            phase_input(header, counts, PhaseOptics(), options)
    header.condenser_na = 0.0
    header.pixel_size_um = 0.0
    with pytest.raises(ValueError, match="no pixel size"):
        phase_input(header, counts, PhaseOptics(), options)


def test_the_phase_command_serves_zenoh_and_http_in_one_process(
    http: httpx.Client, tmp_path: Path
) -> None:
    endpoint = loopback_endpoint()
    instrument = open_session(listen=[endpoint])
    (tmp_path / "frame.key").write_bytes(FRAME_KEY)
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "focustrack_phase",
            "--port",
            str(port),
            "--connect",
            endpoint,
            "--frame-key-file",
            str(tmp_path / "frame.key"),
        ],
        env=os.environ | {"PYTHONUNBUFFERED": "1"},
    )
    results: queue.Queue = queue.Queue()
    subscriber = instrument.declare_subscriber(keys.phase_pattern("s1"), results.put)
    try:
        for _ in range(300):
            assert process.poll() is None, "the phase service exited"
            try:
                health = http.get(f"http://127.0.0.1:{port}/healthz").json()
                if health["status"] == "ok":  # the REST app, and the session linked
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        else:
            pytest.fail("the phase service did not come up on HTTP and Zenoh")
        time.sleep(0.5)  # let its subscription reach the instrument's side
        truth_rad, counts = camera_counts(seed=6)
        publisher = PixelPublisher(instrument, signer=FrameSigner(FRAME_KEY))
        publish(publisher, header_of(3, REFERENCE_Z_UM + OFFSETS_UM), counts)
        sample = results.get(timeout=30)
        result = phase_pb2.PhaseResult.FromString(sample.attachment.to_bytes())
        phase_rad, _ = codec.phase_field(result, sample.payload.to_bytes())
        assert correlation(phase_rad, truth_rad) > 0.8
    finally:
        subscriber.undeclare()
        process.terminate()
        process.wait(10)
        instrument.close()


class Clock:
    """A clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def frame_samples(
    header: instrument_pb2.ZStackHeader, pixels: np.ndarray
) -> list[tuple[bytes, bytes]]:
    """(payload, attachment) of each whole frame of `pixels` (n, h, w, channels), untagged."""
    describe_stack(header, pixels.shape, pixels.dtype)
    return [
        (pixels[i].tobytes(), codec.frame_header(header, i, pixels[i]).SerializeToString())
        for i in range(len(pixels))
    ]


def test_phase_stacks_are_bounded_in_frames_pixels_bytes_and_time() -> None:
    clock = Clock()
    limits = PhaseLimits(max_frames=4, max_pixels=64 * 64)
    stacks = PhaseStacks(limits, budget_bytes=3 * 64 * 64 * 4, timeout_s=10.0, clock=clock)
    key = keys.zframe_key("s1", 1, 2)
    z_um = REFERENCE_Z_UM + np.array([-2.0, 0.0, 2.0])
    rgb = np.zeros((3, 64, 64, 3), np.uint16)
    rgb[..., 1] = 7  # green
    header = header_of(1, z_um)
    header.channel_order = "RGB"
    samples = frame_samples(header, rgb)
    assert stacks.add(key, lambda: samples[0][0], samples[0][1]) is None
    assert stacks.open_bytes == 3 * 64 * 64 * 4  # the whole stack's counts, taken at once
    # a second stack does not fit beside it: an error result, once
    other = frame_samples(header_of(2, z_um), rgb[..., :1])
    refused = stacks.add(key, lambda: other[0][0], other[0][1])
    assert isinstance(refused, phase_pb2.PhaseResult) and "budget" in refused.error.message
    assert stacks.add(key, lambda: other[1][0], other[1][1]) is None  # ignored from now on
    for payload, attachment in samples[1:]:
        done = stacks.add(key, lambda payload=payload: payload, attachment)
    assert isinstance(done, PhaseStack) and np.all(done.counts == 7)  # the green channel
    assert stacks.open_bytes == 0
    # too many frames, too large frames: refused before anything is held
    many = frame_samples(header_of(3, np.arange(5.0)), np.zeros((5, 8, 8, 1), np.uint16))
    assert "limit is 4" in stacks.add(key, lambda: many[0][0], many[0][1]).error.message
    large = frame_samples(header_of(4, z_um), np.zeros((3, 65, 64, 1), np.uint16))
    assert "limit is 4096" in stacks.add(key, lambda: large[0][0], large[0][1]).error.message
    # a stack whose frames stop coming is dropped after the timeout
    late = frame_samples(header_of(5, z_um), rgb[..., :1])
    assert stacks.add(key, lambda: late[0][0], late[0][1]) is None
    clock.now_s = 10.5
    stacks.expire()
    assert stacks.n_expired == 1 and stacks.open_bytes == 0


def test_a_phase_frame_that_does_not_fit_its_header_gets_an_error_result() -> None:
    """A structured dtype raised a TypeError that killed the worker's thread (no phase again,
    and the instrument's publisher stalled on its queue); a 3-D shape or an index beyond
    the frames was dropped without a word. Each is answered."""
    stacks = PhaseStacks(PhaseLimits(), budget_bytes=1 << 24, timeout_s=10.0)
    key = keys.zframe_key("s1", 1, 2)
    z_um = REFERENCE_Z_UM + np.array([-2.0, 0.0, 2.0])
    good = frame_samples(header_of(1, z_um), np.zeros((3, 8, 8, 1), np.uint16))[0]
    wrong = {
        "not one number per pixel": lambda frame: (  # 8 x 4 pixels of two uint16: the bytes
            setattr(frame.stack, "dtype", "u2,u2"),
            frame.stack.shape.__setitem__(2, 4),
        ),
        "expected (frames, height, width, channels)": lambda frame: frame.stack.shape.pop(),
        "frame 7 of a stack of 3 frames": lambda frame: setattr(frame, "index", 7),
    }
    for sequence, (message, spoil) in enumerate(wrong.items(), start=2):
        frame = instrument_pb2.ZFrameHeader.FromString(good[1])
        frame.stack.sequence = sequence
        spoil(frame)
        answer = stacks.add(key, lambda: good[0], frame.SerializeToString())
        assert isinstance(answer, phase_pb2.PhaseResult), message
        assert message in answer.error.message
        # once: the stack's later frames are ignored (a malformed header was answered for
        # every frame of its stack, 201 results for 201 frames)
        assert stacks.add(key, lambda: good[0], frame.SerializeToString()) is None, message
