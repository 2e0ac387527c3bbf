"""The MMCore backend on Micro-Manager's own C++ demo devices (`mm-test-adapters`: DemoCamera,
Utilities, SequenceTester), no mocks: what it describes, moves and acquires, snapped and
as hardware sequences, its refusals, every device fault as its error (also through the
real shell over Zenoh), a UniMMCore with Python devices, and the command."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import mm_test_adapters
import numpy as np
import pytest
import zenoh
from instrument_process import wait_until_it_answers
from pymmcore_plus import CMMCorePlus
from pymmcore_plus.experimental.unicore import (
    SimpleCameraDevice,
    StageDevice,
    UniMMCore,
    XYStageDevice,
)
from pymmcore_plus.seq_tester import decode_image

from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc, session
from focustrack_instrument_sim import service
from focustrack_instrument_sim.instrument import (
    AcquisitionRefusedError,
    DeviceError,
    DeviceTimeoutError,
    NoImageError,
    Refusal,
    StackPlan,
    StackRequest,
    TargetNotReachedError,
)
from focustrack_instrument_sim.mmcore_backend import (
    MMCoreInstrument,
    core_from_config,
    release_core,
)
from focustrack_instrument_sim.mmcore_options import MMCoreOptions

ADAPTERS = Path(mm_test_adapters.device_adapter_path())
DEMO_CONFIG = ADAPTERS / "MMConfig_demo.cfg"
#: The demo's focus stage (DStage) has no Position limits: the options give them.
OPTIONS = MMCoreOptions(mm_z_min_um=-50.0, mm_z_max_um=50.0, mm_rows=2, mm_cols=3)


def _frames(instrument: MMCoreInstrument, plan: StackPlan) -> list[np.ndarray]:
    """The frames of `plan`, each in an array of its own."""
    return list(instrument.acquire(plan, lambda _: np.empty(plan.frame.shape, plan.frame.dtype)))


@pytest.fixture
def demo() -> CMMCorePlus:
    """A core with the demo configuration (the instrument made of it releases it)."""
    return core_from_config(str(DEMO_CONFIG), [str(ADAPTERS)])  # paths or their text


@pytest.fixture
def instrument(demo: CMMCorePlus) -> Iterator[MMCoreInstrument]:
    opened = MMCoreInstrument(demo, OPTIONS)
    yield opened
    opened.close()


def _sequenced(demo: CMMCorePlus, **options: object) -> MMCoreInstrument:
    """The demo instrument with its focus stage sequencing (DStage's UseSequences)."""
    demo.setProperty("Z", "UseSequences", "Yes")
    return MMCoreInstrument(demo, OPTIONS.model_copy(update=options))


def test_info_is_the_configuration_and_the_options(instrument: MMCoreInstrument) -> None:
    described = instrument.describe()
    frame = described.frame
    assert (frame.height, frame.width, frame.channel_order, frame.dtype, frame.bit_depth) == (
        512, 512, "L", np.dtype(np.uint16), 16
    )  # fmt: skip
    assert described.optics.pixel_size_um == 1.0  # Res10x, the startup objective
    (slide,) = described.slides
    # one field of view apart (512 px of 1 um), from where the stage stood
    assert (slide.name, slide.grid.shape, slide.grid.pitch_um) == ("slide-0", (2, 3), 512.0)
    assert (slide.grid.origin_x_um, slide.grid.origin_y_um) == (0.0, 0.0)
    assert described.z_range_um == (-50.0, 50.0) and described.max_frames == 64
    assert described.default_exposure_s == pytest.approx(0.01)
    assert not described.hardware_sequenced  # DStage sequences only when asked to


def test_binning_overlap_and_slides_come_from_the_core_and_options(demo: CMMCorePlus) -> None:
    demo.setProperty("Camera", "Binning", "2")
    demo.setXYPosition(100.0, 200.0)
    demo.waitForDevice("XY")
    options = OPTIONS.model_copy(update={"mm_overlap": 0.25, "mm_slides": 2})
    instrument = MMCoreInstrument(demo, options)
    try:
        described = instrument.describe()
        assert (described.frame.height, described.optics.pixel_size_um) == (256, 2.0)
        grids = [slide.grid for slide in described.slides]
        assert [grid.pitch_um for grid in grids] == [384.0, 384.0]  # 256 px of 2 um, less 25%
        assert grids[0].origin_x_um == pytest.approx(100.0, abs=0.01)
        assert grids[1].origin_x_um == pytest.approx(26_100.0, abs=0.01)
    finally:
        instrument.close()


@pytest.mark.parametrize(
    ("pixel_type", "shape", "order", "dtype"),
    [("8bit", (512, 512, 1), "L", np.uint8), ("32bitRGB", (512, 512, 3), "RGB", np.uint8)],
)
def test_8_bit_and_rgb_cameras(
    demo: CMMCorePlus, pixel_type: str, shape: tuple[int, ...], order: str, dtype: type
) -> None:
    demo.setProperty("Camera", "PixelType", pixel_type)
    instrument = MMCoreInstrument(demo, OPTIONS)
    try:
        assert instrument.describe().frame.channel_order == order
        (frame,) = _frames(instrument, instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 1.0, 1)))
        assert frame.shape == shape and frame.dtype == dtype and frame.any()
    finally:
        instrument.close()


def test_a_snapped_stack_moves_the_stages_and_exposes(instrument: MMCoreInstrument) -> None:
    core = instrument.core
    plan = instrument.plan(StackRequest("slide-0", 1, 2, -2.0, 0.5, 5, exposure_s=0.002))
    assert (plan.stage_x_um, plan.stage_y_um) == (1024.0, 512.0)
    x_um, y_um = core.getXYPosition()
    assert x_um == pytest.approx(1024.0, abs=0.02) and y_um == pytest.approx(512.0, abs=0.02)
    assert plan.timing.move_distance_um == pytest.approx(np.hypot(1024.0, 512.0), abs=0.1)
    assert plan.timing.exposure_s == pytest.approx(0.01)
    np.testing.assert_allclose(plan.z_um, [-2.0, -1.5, -1.0, -0.5, 0.0])
    frames = _frames(instrument, plan)
    assert len(frames) == 5 and all(f.shape == (512, 512, 1) and f.any() for f in frames)
    assert core.getPosition("Z") == 0.0  # the last frame's z
    assert core.getExposure() == 2.0  # ms
    assert core.getAutoShutter() and not core.getShutterOpen()  # as before the stack


def test_a_sequenced_stack_is_one_hardware_sequence(demo: CMMCorePlus) -> None:
    instrument = _sequenced(demo)
    try:
        described = instrument.describe()
        assert described.hardware_sequenced and described.max_frames == 64
        plan = instrument.plan(StackRequest("slide-0", 0, 1, -1.0, 0.5, 5, exposure_s=0.001))
        frames = _frames(instrument, plan)
        assert len(frames) == 5 and all(f.any() for f in frames)
        assert not demo.isSequenceRunning()
    finally:
        instrument.close()


def _sequence_tester(max_sequence: int) -> CMMCorePlus:
    """SequenceTester's camera and stages, the camera's images saying what the devices were
    doing (MachineReadable), the focus stage sequencing up to `max_sequence` positions."""
    core = CMMCorePlus(mm_path=str(ADAPTERS), adapter_paths=[str(ADAPTERS)])
    core.loadDevice("THub", "SequenceTester", "THub")
    core.initializeDevice("THub")
    for label, name in (("TCamera", "TCamera"), ("TZ", "TZStage"), ("TXY", "TXYStage")):
        core.loadDevice(label, "SequenceTester", name)
        core.setParentLabel(label, "THub")
        if label == "TCamera":
            core.setProperty(label, "ImageMode", "MachineReadable")
        core.initializeDevice(label)
    core.setCameraDevice("TCamera")
    core.setFocusDevice("TZ")
    core.setXYStageDevice("TXY")
    core.setProperty("TZ", "TriggerSequenceMaxLength", str(max_sequence))
    # the stage steps through its sequence as the camera starts each exposure
    core.setProperty("TZ", "TriggerSourceDevice", "TCamera")
    core.setProperty("TZ", "TriggerSourcePort", "ExposureStartEdge")
    return core


def test_a_sequenced_stack_takes_each_frame_at_its_z() -> None:
    core = _sequence_tester(max_sequence=6)
    options = OPTIONS.model_copy(update={"mm_pixel_size_um": 0.5})
    instrument = MMCoreInstrument(core, options)
    try:
        described = instrument.describe()
        assert described.hardware_sequenced and described.max_frames == 6  # the stage's
        assert described.optics.pixel_size_um == 0.5  # no pixel size config: the option's
        with pytest.raises(AcquisitionRefusedError) as refused:
            instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 1.0, 7))
        assert refused.value.reason is Refusal.TOO_MANY_FRAMES
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 1.0, 0.5, 4, exposure_s=0.001))
        packets = [decode_image(frame[..., 0]) for frame in _frames(instrument, plan)]
        assert all(packet.camera_info.is_sequence for packet in packets)
        z_um = [
            next(
                setting.value
                for setting in packet.current_state
                if (setting.device, setting.property) == ("TZStage", "ZPositionUm")
            )
            for packet in packets
        ]
        assert z_um == pytest.approx([1.0, 1.5, 2.0, 2.5])
    finally:
        instrument.close()


@pytest.mark.parametrize(
    ("request_", "reason", "field"),
    [
        (StackRequest("slide-9", 0, 0, 0.0, 1.0, 3), Refusal.UNKNOWN_SLIDE, "slide"),
        (StackRequest("slide-0", 0, 3, 0.0, 1.0, 3), Refusal.TILE_OUTSIDE_SLIDE, "col"),
        (StackRequest("slide-0", 0, 0, 45.0, 1.0, 10), Refusal.Z_OUT_OF_RANGE, "z_low_um"),
        (StackRequest("slide-0", 0, 0, 0.0, 0.1, 65), Refusal.TOO_MANY_FRAMES, "n_frames"),
        (StackRequest("slide-0", 0, 0, 0.0, 1.0, 3, 11.0), Refusal.MALFORMED, "exposure_s"),
        (
            StackRequest("slide-0", 0, 0, 0.0, 1.0, 3, stage_offset_y_um=float("nan")),
            Refusal.MALFORMED,
            "stage_offset_y_um",
        ),
    ],
)
def test_refusals_leave_the_stage_where_it_is(
    instrument: MMCoreInstrument, request_: StackRequest, reason: Refusal, field: str
) -> None:
    with pytest.raises(AcquisitionRefusedError) as refused:
        instrument.plan(request_)
    assert (refused.value.reason, refused.value.field) == (reason, field)
    assert instrument.core.getXYPosition() == pytest.approx([0.0, 0.0], abs=0.02)


def test_a_drivers_error_is_a_device_error(demo: CMMCorePlus) -> None:
    # DStage itself refuses positions beyond its travel (which it does not report)
    instrument = MMCoreInstrument(demo, OPTIONS.model_copy(update={"mm_z_max_um": 10_000.0}))
    try:
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 5_000.0, 1.0, 2))
        with pytest.raises(DeviceError, match='Z: Error in device "Z": Position out of range'):
            _frames(instrument, plan)
    finally:
        instrument.close()


def test_a_stage_that_does_not_finish_in_time_is_a_timeout(demo: CMMCorePlus) -> None:
    instrument = MMCoreInstrument(demo, OPTIONS.model_copy(update={"mm_timeout_s": 0.3}))
    try:
        demo.setProperty("XY", "Velocity", "0.01")  # um/ms: 51 s to the next tile
        started_s = time.perf_counter()
        with pytest.raises(DeviceTimeoutError, match="XY: Wait for device"):
            instrument.plan(StackRequest("slide-0", 0, 1, 0.0, 1.0, 2))
        assert time.perf_counter() - started_s < 2.0
    finally:
        instrument.close()


def test_a_stage_that_stops_short_is_target_not_reached(demo: CMMCorePlus) -> None:
    # DXYStage moves in steps of 0.015 um: it stops 0.005 um from 1024
    instrument = MMCoreInstrument(demo, OPTIONS.model_copy(update={"mm_xy_tolerance_um": 0.001}))
    try:
        with pytest.raises(TargetNotReachedError, match=r"XY: stopped at \(1024.005"):
            instrument.plan(StackRequest("slide-0", 0, 2, 0.0, 1.0, 2))
    finally:
        instrument.close()


def test_a_sequence_slower_than_its_deadline_is_a_timeout(demo: CMMCorePlus) -> None:
    # The demo camera drawing noise streams far slower than 1 ms frames (about 20 ms
    # here); the deadline is the exposures + 10 ms: 74 ms. It is checked while a frame is
    # awaited, not while frames wait to be read, so the sequence is long (over 1 s): a
    # reader descheduled on a loaded machine could otherwise find every frame there.
    demo.setProperty(demo.getCameraDevice(), "Mode", "Noise")
    instrument = _sequenced(demo, mm_timeout_s=0.01)
    try:
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 0.1, 64, exposure_s=0.001))
        with pytest.raises(DeviceTimeoutError, match="of 64 frames by the sequence's deadline"):
            _frames(instrument, plan)
        assert not demo.isSequenceRunning()  # stopped on the way out
    finally:
        instrument.close()


def test_a_camera_that_stops_delivering_is_no_image(demo: CMMCorePlus) -> None:
    instrument = _sequenced(demo)
    try:
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 0.5, 64, exposure_s=0.01))
        threading.Timer(0.1, demo.stopSequenceAcquisition).start()  # as a camera that quits
        with pytest.raises(NoImageError, match=r"the sequence ended after \d+ of 64 frames"):
            _frames(instrument, plan)
    finally:
        instrument.close()


def test_a_core_without_what_a_stack_needs_is_refused(demo: CMMCorePlus) -> None:
    with pytest.raises(ValueError, match="reports no travel limits"):
        MMCoreInstrument(demo, MMCoreOptions())
    demo.setFocusDevice("")
    with pytest.raises(ValueError, match="must name a camera and a focus device"):
        MMCoreInstrument(demo, OPTIONS)
    release_core(demo)


class _Camera(SimpleCameraDevice):
    """A camera whose every pixel is the focus position (um) it was snapped at; a snap
    takes `hang_s` besides (a camera that hangs)."""

    def __init__(self, focus: _Focus) -> None:
        super().__init__()
        self.focus = focus
        self.exposure_ms = 10.0
        self.hang_s = 0.0

    def sensor_shape(self) -> tuple[int, int]:
        return (8, 6)

    def dtype(self) -> np.dtype:
        return np.dtype(np.uint16)

    def get_exposure(self) -> float:
        return self.exposure_ms

    def set_exposure(self, exposure: float) -> None:
        self.exposure_ms = exposure

    def snap(self, buffer: np.ndarray) -> dict[str, object]:
        time.sleep(self.hang_s)
        buffer[:] = round(self.focus.z_um)
        return {}


class _Focus(StageDevice):
    z_um = 0.0

    def set_position_um(self, val: float) -> None:
        self.z_um = val

    def get_position_um(self) -> float:
        return self.z_um

    def set_origin(self) -> None:
        self.z_um = 0.0

    def home(self) -> None:
        self.z_um = 0.0

    def stop(self) -> None:
        """Moves are instantaneous."""


class _XY(XYStageDevice):
    xy_um = (0.0, 0.0)

    def set_position_um(self, x: float, y: float) -> None:
        self.xy_um = (x, y)

    def get_position_um(self) -> tuple[float, float]:
        return self.xy_um

    def set_origin_x(self) -> None:
        self.xy_um = (0.0, self.xy_um[1])

    def set_origin_y(self) -> None:
        self.xy_um = (self.xy_um[0], 0.0)

    def home(self) -> None:
        self.xy_um = (0.0, 0.0)

    def stop(self) -> None:
        """Moves are instantaneous."""


def _python_devices(camera: _Camera) -> UniMMCore:
    """A UniMMCore with `camera`, its focus stage and an XY stage, pure Python."""
    core = UniMMCore()
    for label, device in (("Camera", camera), ("XY", _XY()), ("Z", camera.focus)):
        core.loadPyDevice(label, device)
        core.initializeDevice(label)
    core.setCameraDevice("Camera")
    core.setXYStageDevice("XY")
    core.setFocusDevice("Z")
    return core


def test_a_unimmcore_with_python_devices_is_served() -> None:
    core = _python_devices(_Camera(_Focus()))
    options = OPTIONS.model_copy(update={"mm_pixel_size_um": 0.25})
    instrument = MMCoreInstrument(core, options)
    try:
        described = instrument.describe()
        assert not described.hardware_sequenced
        assert (described.frame.height, described.frame.width) == (8, 6)  # sensor_shape
        assert described.slides[0].grid.pitch_um == 1.5  # 6 px of 0.25 um
        plan = instrument.plan(StackRequest("slide-0", 1, 1, 3.0, 2.0, 3))
        assert core.getXYPosition() == pytest.approx([1.5, 1.5])
        assert [int(f[0, 0, 0]) for f in _frames(instrument, plan)] == [3, 5, 7]
    finally:
        instrument.close()


def test_a_camera_that_hangs_in_a_snap_is_a_timeout() -> None:
    camera = _Camera(_Focus())
    options = OPTIONS.model_copy(update={"mm_pixel_size_um": 0.25, "mm_timeout_s": 0.2})
    instrument = MMCoreInstrument(_python_devices(camera), options)
    try:
        plan = instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 1.0, 2, exposure_s=0.01))
        camera.hang_s = 1.0
        started_s = time.perf_counter()
        with pytest.raises(DeviceTimeoutError, match=r"Camera: no image 0.2 s after the snap"):
            _frames(instrument, plan)
        assert time.perf_counter() - started_s < 0.6
    finally:
        instrument.close()  # after the hung snap ends


@pytest.fixture
def served(demo: CMMCorePlus) -> Iterator[tuple[MMCoreInstrument, zenoh.Session]]:
    """The demo instrument behind the real shell (in this process, named "mm") on a Zenoh
    session of its own, and a client's session, over loopback TCP."""
    endpoint = session.loopback_endpoint()
    instrument = MMCoreInstrument(demo, OPTIONS.model_copy(update={"mm_timeout_s": 0.3}))
    with (
        session.open_session(listen=[endpoint]) as instrument_side,
        session.open_session(connect=[endpoint]) as client,
    ):
        shell = service.InstrumentService(instrument, instrument_side, "mm")
        shell.start()
        thread = threading.Thread(target=shell.serve)
        thread.start()
        try:
            yield instrument, client
        finally:
            shell.stop.set()
            thread.join()
            shell.close()
            instrument.close()


def _acquire(client: zenoh.Session, name: str, **fields: object) -> instrument_pb2.AcquireReply:
    """Acquire 3 frames from -1 um of tile (0, 0) of slide-0, or what `fields` say."""
    defaults = dict(slide="slide-0", row=0, col=0, z_low_um=-1.0, z_step_um=0.5, n_frames=3)
    request = instrument_pb2.AcquireRequest(**{**defaults, **fields})
    return rpc.call(client, keys.acquire_key(name), request, instrument_pb2.AcquireReply)


def test_device_faults_are_error_replies_through_the_shell(
    served: tuple[MMCoreInstrument, zenoh.Session],
) -> None:
    instrument, client = served
    info = rpc.call(client, keys.info_key("mm"), instrument_pb2.AcquireRequest(),
                    instrument_pb2.InstrumentInfo)  # fmt: skip
    assert (info.width, info.height, info.channel_order, info.bit_depth) == (512, 512, "L", 16)
    assert (info.z_min_um, info.z_max_um, info.pixel_size_um) == (-50.0, 50.0, 1.0)
    assert not info.hardware_sequenced and [s.cols for s in info.slides] == [3]

    frames: list[tuple[instrument_pb2.ZFrameHeader, np.ndarray]] = []
    assembler = codec.FrameAssembler()

    def on_frame(sample: zenoh.Sample) -> None:
        if (frame := assembler.add_sample(sample)) is not None:
            frames.append(frame)

    with client.declare_subscriber(keys.zframe_pattern("slide-0"), on_frame):
        time.sleep(0.5)  # let the subscription reach the instrument
        reply = _acquire(client, "mm", col=1, sequence=1)
        for _ in range(100):
            if len(frames) == 3:
                break
            time.sleep(0.05)
    assert [header.index for header, _ in frames] == [0, 1, 2]
    assert all(frame.shape == (512, 512, 1) and frame.dtype == np.uint16 for _, frame in frames)
    assert reply.header.stage_x_um == 512.0 and list(reply.header.z_um) == [-1.0, -0.5, 0.0]

    instrument.core.setProperty("XY", "Velocity", "0.01")  # a stage that takes a minute
    started_s = time.perf_counter()
    with pytest.raises(rpc.RemoteError) as timed_out:
        _acquire(client, "mm", col=2, sequence=2)
    assert timed_out.value.error.code == common_pb2.ERROR_CODE_DEVICE_TIMEOUT
    assert "XY: Wait for device" in timed_out.value.error.message
    assert time.perf_counter() - started_s < 3.0

    with pytest.raises(rpc.RemoteError) as refused:  # the shell keeps answering
        _acquire(client, "mm", z_low_um=60.0, sequence=3)
    assert refused.value.error.code == common_pb2.ERROR_CODE_Z_OUT_OF_RANGE


def _command(*options: str) -> list[str]:
    return [
        sys.executable, "-m", "focustrack_instrument_sim", "--backend", "mmcore",
        "--mm-config", str(DEMO_CONFIG), "--mm-adapter-path", str(ADAPTERS), *options,
    ]  # fmt: skip


def test_the_command_serves_the_configuration_and_exits_cleanly() -> None:
    endpoint = session.loopback_endpoint()
    command = _command("--listen", endpoint, "--name", "mm", "--mm-z-min-um", "-50",
                       "--mm-z-max-um", "50", "--mm-rows", "2")  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    try:
        with session.open_session(connect=[endpoint], connect_timeout_s=60) as client:
            wait_until_it_answers(client, "mm", process)
            reply = _acquire(client, "mm", row=1, sequence=5)
        assert reply.header.stage_y_um == 512.0 and len(reply.header.z_um) == 3
    finally:
        process.terminate()
        _, stderr = process.communicate(timeout=20)
    assert process.returncode == 0, stderr[-2000:]
    assert "FATAL" not in stderr and "Could not find a compatible" not in stderr


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (("--mm-config", "/nonexistent.cfg"), "--mm-config /nonexistent.cfg: no such file"),
        ((), "reports no travel limits: give the range"),
    ],
)
def test_the_command_refuses_what_it_cannot_serve(options: tuple[str, ...], message: str) -> None:
    ran = subprocess.run(_command(*options), capture_output=True, text=True, timeout=60)
    assert ran.returncode == 2 and message in ran.stderr, ran.stderr[-2000:]
    assert "FATAL" not in ran.stderr


def test_a_configuration_that_does_not_load_ends_the_command(tmp_path: Path) -> None:
    config = tmp_path / "MMConfig.cfg"
    config.write_text("Device,Camera,NoSuchAdapter,DCam\n")
    ran = subprocess.run(_command("--mm-config", str(config)), capture_output=True, text=True,
                         timeout=60)  # fmt: skip
    assert ran.returncode == 1, ran.stderr[-2000:]
    assert f"the instrument did not open: configuration {config}:" in ran.stderr


#: Open the demo, take a snapped and a sequenced stack, close: what every process does.
ROUND_TRIP = f"""
from pathlib import Path
import numpy as np
from focustrack_instrument_sim.instrument import StackRequest
from focustrack_instrument_sim.mmcore_backend import MMCoreInstrument, core_from_config
from focustrack_instrument_sim.mmcore_options import MMCoreOptions
for sequence in (False, True):
    core = core_from_config(Path({str(DEMO_CONFIG)!r}), [Path({str(ADAPTERS)!r})])
    core.setProperty("Z", "UseSequences", "Yes")
    options = MMCoreOptions(mm_z_min_um=-5, mm_z_max_um=5, mm_sequence=sequence)
    instrument = MMCoreInstrument(core, options)
    plan = instrument.plan(StackRequest("slide-0", 0, 0, 0.0, 1.0, 3, 0.001))
    for frame in instrument.acquire(plan, lambda _: np.empty(plan.frame.shape, plan.frame.dtype)):
        pass
    instrument.close()
"""


def test_processes_that_close_the_instrument_exit_cleanly() -> None:
    # Before close() detached the core's callback relay, most such processes aborted at
    # exit ("FATAL: exception not rethrown"): a few at once catch a regression.
    processes = [
        subprocess.Popen([sys.executable, "-c", ROUND_TRIP], stderr=subprocess.PIPE, text=True)
        for _ in range(4)
    ]
    for process in processes:
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0 and "FATAL" not in stderr, stderr[-2000:]


def test_the_mmcore_backend_needs_a_configuration() -> None:
    command = [sys.executable, "-m", "focustrack_instrument_sim", "--backend", "mmcore"]
    ran = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert ran.returncode == 2 and "--backend mmcore needs --mm-config FILE" in ran.stderr


def test_adapter_folders_from_the_environment_are_a_list(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FOCUSTRACK_INSTRUMENT_MM_ADAPTER_PATH", "/opt/mm,/opt/more")
    settings = service.InstrumentSettings.load()
    assert settings.mm_adapter_path == [Path("/opt/mm"), Path("/opt/more")]
