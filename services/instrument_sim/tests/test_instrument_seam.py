"""The Zenoh shell over an instrument that is not the simulator: a tiny in-test backend,
served over real Zenoh sessions on loopback (info, acquisitions, kept frames, refusals,
failed devices), the command's backends, and what the shell imports."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh

from focustrack_core.geometry import ScanGrid
from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc, session
from focustrack_instrument_sim import backends, service
from focustrack_instrument_sim.backends import Backend
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    Description,
    DeviceError,
    DeviceTimeoutError,
    FrameFormat,
    Frames,
    Instrument,
    NoImageError,
    OpticsInfo,
    Refusal,
    SlideLayout,
    StackPlan,
    StackRequest,
    StackTiming,
    TargetNotReachedError,
)

#: Monochrome 8-bit frames of 6 x 8 pixels: nothing like the simulator's.
FRAME = FrameFormat(height=6, width=8, channel_order="L", dtype=np.dtype(np.uint8), bit_depth=8)
GRID = ScanGrid(2, 3, pitch_um=500.0, origin_x_um=1000.0)
MAX_FRAMES = 5


class ConstantInstrument:
    """A fake microscope: frame k of every stack is all k + 1. It raises `failure` (when
    set) instead of its second frame, and stops after `frames_delivered` frames (when set)."""

    def __init__(self) -> None:
        self.failure: Exception | None = None
        self.frames_delivered: int | None = None
        self.clock_s = 0.0

    def describe(self) -> Description:
        return Description(
            slides=(SlideLayout("glass", GRID),),
            frame=FRAME,
            optics=OpticsInfo(0.65, 0.25, 10.0, 0.55, 1.0, 9.5),
            z_range_um=(-50.0, 50.0),
            max_frames=MAX_FRAMES,
            default_exposure_s=0.02,
            hardware_sequenced=True,
        )

    def plan(self, request: StackRequest) -> StackPlan:
        n_frames = request.n_frames
        if n_frames > MAX_FRAMES:
            raise AcquisitionRefusedError(
                Refusal.TOO_MANY_FRAMES, f"at most {MAX_FRAMES} frames", "n_frames"
            )
        exposure_s = request.exposure_s or 0.02
        timing = StackTiming(250.0, 0.1, 0.01 * n_frames, exposure_s * n_frames, 0.0)
        self.clock_s += timing.total_s
        x_um, y_um = GRID.stage_xy_um(request.row, request.col)
        z_um = request.z_low_um + request.z_step_um * np.arange(n_frames)
        return StackPlan(
            request.slide, request.row, request.col, x_um, y_um, z_um, exposure_s, FRAME,
            0.65, timing, self.clock_s,
        )  # fmt: skip

    def acquire(self, plan: StackPlan, out: Callable[[int], np.ndarray]) -> Frames:
        for k in range(plan.n_frames if self.frames_delivered is None else self.frames_delivered):
            if k == 1 and self.failure is not None:
                raise self.failure
            frame = out(k)
            frame[...] = k + 1
            yield frame

    def close(self) -> None:
        pass


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[ConstantInstrument, zenoh.Session]]:
    """The fake instrument behind the real shell (in this process, named "fake"), and a
    client's session."""
    endpoint = session.loopback_endpoint()
    fake = ConstantInstrument()
    with (
        session.open_session(listen=[endpoint]) as instrument_side,
        session.open_session(connect=[endpoint]) as client,
    ):
        shell = service.InstrumentService(fake, instrument_side, "fake")
        shell.start()
        thread = threading.Thread(target=shell.serve)
        thread.start()
        try:
            yield fake, client
        finally:
            shell.stop.set()
            thread.join()
            shell.close()


@pytest.fixture
def instrument(served: tuple[ConstantInstrument, zenoh.Session]) -> Iterator[ConstantInstrument]:
    """The fake instrument, working again after the test."""
    fake, _ = served
    yield fake
    fake.failure, fake.frames_delivered = None, None


@pytest.fixture
def client(served: tuple[ConstantInstrument, zenoh.Session]) -> zenoh.Session:
    return served[1]


def _acquire(
    client: zenoh.Session, sequence: int, n_frames: int = 3
) -> instrument_pb2.AcquireReply:
    request = instrument_pb2.AcquireRequest(
        slide="glass", row=1, col=2, z_low_um=-1.0, z_step_um=0.5, n_frames=n_frames,
        sequence=sequence,
    )  # fmt: skip
    return rpc.call(client, keys.acquire_key("fake"), request, instrument_pb2.AcquireReply)


def test_info_is_the_instruments_description(client: zenoh.Session) -> None:
    info = rpc.call(client, keys.info_key("fake"), instrument_pb2.AcquireRequest(),
                    instrument_pb2.InstrumentInfo)  # fmt: skip
    assert info.instrument == "fake"
    assert [(s.slide, s.rows, s.cols, s.pitch_um, s.origin_x_um) for s in info.slides] == [
        ("glass", 2, 3, 500.0, 1000.0)
    ]
    assert (info.width, info.height, info.channel_order, info.bit_depth) == (8, 6, "L", 8)
    assert (info.z_min_um, info.z_max_um, info.max_frames) == (-50.0, 50.0, MAX_FRAMES)
    assert (info.numerical_aperture, info.depth_of_field_um) == (0.25, 9.5)
    assert info.default_exposure_s == 0.02 and info.hardware_sequenced


def test_acquired_frames_are_published_kept_and_answered(client: zenoh.Session) -> None:
    frames: list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]] = []
    stacks: list[tuple[instrument_pb2.ZStackHeader, np.ndarray]] = []
    assembler = codec.FrameAssembler()

    def on_frame(sample: zenoh.Sample) -> None:
        if (frame := assembler.add_sample(sample)) is not None:
            frames.append(frame)

    with (
        client.declare_subscriber(keys.zframe_pattern("glass"), on_frame),
        client.declare_subscriber(
            keys.zstack_pattern("glass"), lambda s: stacks.append(codec.decode_zstack_sample(s))
        ),
    ):
        time.sleep(0.5)  # let the subscriptions reach the instrument
        reply = _acquire(client, sequence=7)
        for _ in range(100):
            if len(frames) == 3 and stacks:
                break
            time.sleep(0.1)
    assert [header.index for header, _ in frames] == [0, 1, 2]
    for header, frame in frames:
        assert frame.shape == (6, 8, 1) and frame.dtype == np.uint8
        assert np.all(frame == header.index + 1)
    header, pixels = stacks[0]
    assert pixels.shape == (3, 6, 8, 1) and list(np.unique(pixels)) == [1, 2, 3]
    assert (header.stage_x_um, header.stage_y_um) == (2000.0, 500.0)
    np.testing.assert_allclose(header.z_um, [-1.0, -0.5, 0.0])
    assert (header.channel_order, header.pixel_size_um, header.sequence) == ("L", 0.65, 7)
    assert reply.header == header
    assert reply.timing.move_distance_um == 250.0
    assert reply.timing.total_s == pytest.approx(0.1 + 0.03 + 0.06)

    # The shell keeps the frames it published, and answers them again.
    request = instrument_pb2.FramesRequest(slide="glass", row=1, col=2, sequence=7, indices=[2])
    replies = list(client.get(keys.frames_key("fake"), payload=request.SerializeToString(),
                              timeout=10, consolidation=zenoh.ConsolidationMode.NONE))  # fmt: skip
    (kept_header, kept), = (codec.decode_zframe_sample(r.ok) for r in replies)  # fmt: skip
    assert kept_header.index == 2 and np.all(kept == 3) and kept.shape == (6, 8, 1)


@pytest.mark.parametrize(
    ("failure", "code"),
    [
        (DeviceError("Camera", "driver error 12"), common_pb2.ERROR_CODE_DEVICE_FAILURE),
        (DeviceTimeoutError("ZStage", "busy after 5 s"), common_pb2.ERROR_CODE_DEVICE_TIMEOUT),
        (
            TargetNotReachedError("ZStage", "at 3.2 um, sent to 3.0 um"),
            common_pb2.ERROR_CODE_TARGET_NOT_REACHED,
        ),
        (NoImageError("Camera", "no image in the buffer"), common_pb2.ERROR_CODE_NO_IMAGE),
        (RuntimeError("a bug in the backend"), common_pb2.ERROR_CODE_INTERNAL),
    ],
)
def test_a_failed_device_gets_its_error_reply_and_the_service_keeps_answering(
    instrument: ConstantInstrument, client: zenoh.Session, failure: Exception, code: int
) -> None:
    instrument.failure = failure
    with pytest.raises(rpc.RemoteError) as failed:
        _acquire(client, sequence=20)
    assert failed.value.error.code == code
    assert str(failure) in failed.value.error.message
    with pytest.raises(rpc.RemoteError) as gone:  # a stack cut short is not kept
        rpc.call(client, keys.frames_key("fake"),
                 instrument_pb2.FramesRequest(slide="glass", row=1, col=2, sequence=20),
                 instrument_pb2.AcquireReply)  # fmt: skip
    assert gone.value.error.code == common_pb2.ERROR_CODE_FRAMES_GONE

    instrument.failure = None
    assert len(_acquire(client, sequence=21).header.z_um) == 3


def test_a_stack_cut_short_is_no_image(instrument: ConstantInstrument, client) -> None:
    instrument.frames_delivered = 2
    with pytest.raises(rpc.RemoteError) as short:
        _acquire(client, sequence=30)
    assert short.value.error.code == common_pb2.ERROR_CODE_NO_IMAGE
    assert "2 of 3 frames" in short.value.error.message


def test_a_refusal_of_the_instrument_names_its_field(client: zenoh.Session) -> None:
    with pytest.raises(rpc.RemoteError) as refused:
        _acquire(client, sequence=40, n_frames=MAX_FRAMES + 1)
    assert refused.value.error.code == common_pb2.ERROR_CODE_TOO_MANY_FRAMES
    assert refused.value.error.field == "n_frames"


def test_truth_is_served_only_by_an_instrument_that_has_it(client: zenoh.Session) -> None:
    with pytest.raises(ValueError, match="ConstantInstrument has no ground truth"):
        service.InstrumentService(ConstantInstrument(), client, "fake", serve_truth=True)


def _run(
    monkeypatch: pytest.MonkeyPatch, open_instrument: Callable[[service.Settings], Instrument],
    *options: str,
) -> int:  # fmt: skip
    """The command with its backend (sim, the default) opening with `open_instrument`."""
    monkeypatch.setitem(backends.BACKENDS, "sim", Backend("a test's", open_instrument))
    return service.main(["--connect", session.loopback_endpoint(), *options])


def test_the_command_ends_when_the_instrument_does_not_open(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def unplugged(_settings: service.Settings) -> Instrument:
        raise DeviceError("Camera", "not connected")

    assert _run(monkeypatch, unplugged) == 1
    assert "the instrument did not open: Camera: not connected" in caplog.text


def test_the_command_refuses_serve_truth_without_truth(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    assert _run(monkeypatch, lambda _: ConstantInstrument(), "--serve-truth") == 2
    assert "--serve-truth: ConstantInstrument has no ground truth" in caplog.text


#: What the simulator loads when it opens: its modules, scipy and OpenCV.
SIMULATOR = {
    *(f"focustrack_instrument_sim.{name}" for name in
      ("microscope", "optics", "specimen", "camera", "stage", "simulated")),
    "scipy", "cv2",
}  # fmt: skip

#: What the MMCore backend loads when it opens: its module and pymmcore-plus.
MMCORE = {"focustrack_instrument_sim.mmcore_backend", "pymmcore_plus", "pymmcore"}


@pytest.mark.parametrize(
    ("command", "status"),
    [
        (["-c", "import focustrack_instrument_sim.service"], 0),
        (["-m", "focustrack_instrument_sim", "--help"], 0),
        (["-m", "focustrack_instrument_sim", "--queue-depth", "0"], 2),  # refused
    ],
)
def test_the_shell_its_help_and_a_bad_option_load_no_backend(
    command: list[str], status: int
) -> None:
    ran = subprocess.run(
        [sys.executable, "-X", "importtime", *command], capture_output=True, text=True
    )
    assert ran.returncode == status, ran.stderr[-2000:]
    imported = {
        line.rsplit("|", 1)[-1].strip()
        for line in ran.stderr.splitlines()
        if line.startswith("import time:")
    }
    assert {
        "focustrack_instrument_sim.simulator_options",
        "focustrack_instrument_sim.mmcore_options",
    } <= imported  # declarations only
    assert not (SIMULATOR | MMCORE) & imported
