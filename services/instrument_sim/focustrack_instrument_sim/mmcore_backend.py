"""A real microscope through Micro-Manager's device layer (`--backend mmcore`).

`MMCoreInstrument` serves a pymmcore-plus `CMMCorePlus` as an `Instrument`: the core's
camera, focus device and XY stage (the roles its configuration names), its pixel size
configuration (binning included) and the camera's current exposure. A stack is either a
hardware sequence, where the focus device takes a sequence of positions
(`isStageSequenceable`) and steps through it on the camera's triggers while the camera
streams (`startSequenceAcquisition`), or a focus move, a wait and a snap per frame
(`--no-mm-sequence`, or a focus device that cannot sequence); `Description.hardware_sequenced`
says which.

Micro-Manager knows no slides: they are declared by the options (`MMCoreOptions`), by
default one slide of one tile where the stage stands, tiles a field of view apart.

Every device call is bounded and its failure is a `DeviceError`: pymmcore raises
RuntimeError for a driver's error (a `DeviceError` naming the device), and for a
`waitForDevice` past the core's timeout (`--mm-timeout-s`: a `DeviceTimeoutError`); a
snap runs on a thread of its own and is waited for as long as its exposure and the
timeout; a sequence has a deadline (its exposures and the timeout); a stage that stops
farther from its target than the tolerance is a `TargetNotReachedError`; a camera that
gives no image, or a sequence that ends short, is a `NoImageError`.

The instrument takes the core over: `close` stops it and unloads its devices.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymmcore_plus import CMMCorePlus

from focustrack_core.geometry import ScanGrid
from focustrack_instrument_sim.instrument import (
    Description,
    DeviceError,
    DeviceTimeoutError,
    FrameFormat,
    Frames,
    ImagingConditions,
    NoImageError,
    OpticsInfo,
    SlideLayout,
    StackPlan,
    StackRequest,
    StackTiming,
    TargetNotReachedError,
    check_request,
    depth_of_field_um,
)
from focustrack_instrument_sim.mmcore_options import MMCoreOptions

#: How often a sequence acquisition is polled for its next image, s: far below a frame.
POLL_S = 0.0002


@contextmanager
def device_errors(device: str, *, image: bool = False) -> Iterator[None]:
    """A driver's error within (pymmcore raises RuntimeError, and OSError for a configuration
    that does not load) as a DeviceError of `device`: DeviceTimeoutError where MMCore says
    a wait timed out, NoImageError from the calls that read an image (`image`)."""
    try:
        yield
    except (RuntimeError, OSError) as error:
        message = str(error)
        if "timed out" in message:
            raise DeviceTimeoutError(device, message) from error
        if image:
            raise NoImageError(device, message) from error
        raise DeviceError(device, message) from error


def core_from_config(config: Path | str, adapter_paths: Sequence[Path | str] = ()) -> CMMCorePlus:
    """A core with the devices of the Micro-Manager configuration `config`, from the device
    adapters in `adapter_paths` (none: those of the Micro-Manager installation pymmcore-plus
    finds); paths or their text. ValueError for a missing file or folder; DeviceError when
    the configuration does not load (a device that does not initialise, a line MMCore
    refuses)."""
    config, adapters = Path(config), [Path(folder) for folder in adapter_paths]
    if not config.is_file():
        raise ValueError(f"--mm-config {config}: no such file")
    for folder in adapters:
        if not folder.is_dir():
            raise ValueError(f"--mm-adapter-path {folder}: no such folder")
    folders = [str(folder) for folder in adapters]
    # Given adapter folders, pymmcore-plus need not look for an installation (and log an
    # error when it finds none): the first folder stands for it.
    core = CMMCorePlus(mm_path=folders[0] if folders else None, adapter_paths=folders)
    try:
        with device_errors(f"configuration {config}"):
            core.loadSystemConfiguration(str(config))
    except DeviceError:
        release_core(core)
        raise
    return core


def release_core(core: CMMCorePlus) -> None:
    """Stop `core`'s acquisition, unload its devices and detach its event relay."""
    with suppress(RuntimeError):  # a driver failing now cannot stop the unloading
        if core.isSequenceRunning():
            core.stopSequenceAcquisition()
    core.unloadAllDevices()
    # MMCore calls the relay from its devices' threads; one such call after the
    # interpreter began to exit aborts the process ("FATAL: exception not rethrown").
    super(CMMCorePlus, core).registerCallback(None)


def frame_format(core: CMMCorePlus) -> FrameFormat:
    """The frames of the core's camera as they are now: mono 8 or 16 bit ("L") or RGB32
    (pymmcore-plus gives (height, width, 3) RGB). ValueError for another pixel type."""
    camera = core.getCameraDevice()
    with device_errors(camera):
        height, width = core.getImageHeight(), core.getImageWidth()
        components, itemsize = core.getNumberOfComponents(), core.getBytesPerPixel()
        bit_depth = core.getImageBitDepth()
    if height < 1 or width < 1:
        raise ValueError(f"camera {camera!r} reports frames of {width} x {height} pixels")
    if components == 1 and itemsize in (1, 2):
        return FrameFormat(height, width, "L", np.dtype(f"uint{8 * itemsize}"), bit_depth)
    if components == 4 and itemsize == 4:
        return FrameFormat(height, width, "RGB", np.dtype(np.uint8), min(bit_depth, 8))
    raise ValueError(
        f"camera {camera!r}: pixels of {components} component(s) in {itemsize} byte(s) are "
        "not served; choose mono 8 or 16 bit, or RGB32 (its PixelType property)"
    )


@dataclass(frozen=True)
class MMCorePlan(StackPlan):
    """A plan of the MMCore backend: whether its frames come as a hardware sequence."""

    sequenced: bool = False


class MMCoreInstrument:
    """A pymmcore-plus core (a `CMMCorePlus`, or a `UniMMCore` with Python devices) as an
    `Instrument`, with the slides, limits and optics of `options` (see the module's doc).

    Raises ValueError when the core lacks what a stack needs (a camera, a focus device, a
    pixel size; an XY stage for more than one tile) or the options do not fit it, and
    DeviceError when a device does not answer.
    """

    def __init__(self, core: CMMCorePlus, options: MMCoreOptions | None = None) -> None:
        self.core = core
        self.options = options = options or MMCoreOptions()
        self.camera, self.focus = core.getCameraDevice(), core.getFocusDevice()
        self.xy_stage = core.getXYStageDevice()
        if not self.camera or not self.focus:
            raise ValueError(
                "the configuration must name a camera and a focus device (Core-Camera, "
                f"Core-Focus); it names camera {self.camera!r}, focus {self.focus!r}"
            )
        core.setTimeoutMs(max(1, round(options.mm_timeout_s * 1000)))
        self.frame = frame_format(core)
        with device_errors(self.camera):
            pixel_size_um = core.getPixelSizeUm() or options.mm_pixel_size_um
            self.default_exposure_s = core.getExposure() / 1000.0
        if pixel_size_um is None:
            raise ValueError(
                "no pixel size configuration matches the microscope's state: define one "
                "(ConfigPixelSize and PixelSize_um lines) for the objective in use, or give "
                "--mm-pixel-size-um"
            )
        self.z_range_um = self._z_range_um()
        with device_errors(self.focus):
            self.sequenced = options.mm_sequence and core.isStageSequenceable(self.focus)
            max_frames = options.mm_max_frames
            if self.sequenced:  # a stack is one sequence of the focus device
                max_frames = min(max_frames, core.getStageSequenceMaxLength(self.focus))
        self._description = Description(
            slides=self._slides(pixel_size_um),
            frame=self.frame,
            optics=OpticsInfo(
                pixel_size_um=pixel_size_um,
                numerical_aperture=options.mm_na,
                magnification=options.mm_magnification,
                wavelength_um=options.mm_wavelength_um,
                refractive_index=options.mm_refractive_index,
                depth_of_field_um=depth_of_field_um(
                    options.mm_wavelength_um,
                    options.mm_refractive_index,
                    options.mm_na,
                    pixel_size_um,
                ),
            ),
            z_range_um=self.z_range_um,
            max_frames=max_frames,
            default_exposure_s=self.default_exposure_s,
            hardware_sequenced=self.sequenced,
        )
        self._grids = {slide.name: slide.grid for slide in self._description.slides}
        # In every stack's header: what the options say. The condenser's NA and the
        # camera's gain and offset are not known here (0).
        self.imaging = ImagingConditions(
            wavelength_um=options.mm_wavelength_um, objective_na=options.mm_na
        )
        # Snaps run here so that a camera that never returns is waited for no longer than
        # its exposure and the timeout (pymmcore releases the GIL within snapImage).
        self._snapper = ThreadPoolExecutor(1, thread_name_prefix="mmcore-snap")
        self._snapping: Future[None] | None = None  # the last snap
        self._opened_s = time.perf_counter()

    def _z_range_um(self) -> tuple[float, float]:
        """(low, high) focus positions a stack may reach, um: the options', else the focus
        device's Position limits; ValueError when neither says."""
        core, options, focus = self.core, self.options, self.focus
        low, high = options.mm_z_min_um, options.mm_z_max_um
        with device_errors(focus):
            if core.hasProperty(focus, "Position") and core.hasPropertyLimits(focus, "Position"):
                low = core.getPropertyLowerLimit(focus, "Position") if low is None else low
                high = core.getPropertyUpperLimit(focus, "Position") if high is None else high
        if low is None or high is None:
            raise ValueError(
                f"focus device {focus!r} reports no travel limits: give the range stacks may "
                "reach with --mm-z-min-um and --mm-z-max-um"
            )
        if not low < high:
            raise ValueError(f"the focus range must be low < high, got {low}..{high} um")
        return (low, high)

    def _slides(self, pixel_size_um: float) -> tuple[SlideLayout, ...]:
        """The slides of the options: tile (0, 0) of slide-0 at the origin (default: where
        the stage is), the next slides `mm_slide_spacing_um` further in x."""
        options = self.options
        x_um, y_um = 0.0, 0.0
        if self.xy_stage:
            with device_errors(self.xy_stage):
                x_um, y_um = self.core.getXYPosition(self.xy_stage)
        elif options.mm_slides * options.mm_rows * options.mm_cols > 1:
            raise ValueError("the configuration names no XY stage (Core-XYStage): one tile only")
        field_of_view_um = pixel_size_um * min(self.frame.height, self.frame.width)
        pitch_um = options.mm_pitch_um or field_of_view_um * (1.0 - options.mm_overlap)
        origin_x_um = x_um if options.mm_origin_x_um is None else options.mm_origin_x_um
        origin_y_um = y_um if options.mm_origin_y_um is None else options.mm_origin_y_um
        return tuple(
            SlideLayout(
                f"slide-{index}",
                ScanGrid(
                    options.mm_rows,
                    options.mm_cols,
                    pitch_um,
                    origin_x_um + index * options.mm_slide_spacing_um,
                    origin_y_um,
                ),
            )
            for index in range(options.mm_slides)
        )

    def describe(self) -> Description:
        return self._description

    def plan(self, request: StackRequest) -> MMCorePlan:
        """Check `request` and move the XY stage to its tile, off its place by the request's
        stage offset (the move is timed; the frames' cost is their exposures, their clock
        an estimate)."""
        exposure_s = self.default_exposure_s if request.exposure_s is None else request.exposure_s
        grid = check_request(
            request, exposure_s, self._grids, self.z_range_um, self._description.max_frames
        )
        x_um, y_um = grid.stage_xy_um(request.row, request.col)
        x_um, y_um = x_um + request.stage_offset_x_um, y_um + request.stage_offset_y_um
        started_s = time.perf_counter()
        distance_um = self._move_xy(x_um, y_um) if self.xy_stage else 0.0
        move_s = time.perf_counter() - started_s
        n_frames = request.n_frames
        timing = StackTiming(distance_um, move_s, 0.0, n_frames * exposure_s, 0.0)
        return MMCorePlan(
            slide=request.slide,
            row=request.row,
            col=request.col,
            stage_x_um=x_um,
            stage_y_um=y_um,
            z_um=request.z_low_um + request.z_step_um * np.arange(n_frames),
            exposure_s=exposure_s,
            frame=self.frame,
            pixel_size_um=self._description.optics.pixel_size_um,
            timing=timing,
            clock_s=time.perf_counter() - self._opened_s + timing.exposure_s,
            sequenced=self.sequenced,
            purpose=request.purpose,
            reference_z_um=request.reference_z_um,
            imaging=self.imaging,
        )

    def _move_xy(self, x_um: float, y_um: float) -> float:
        """Move the XY stage to (x_um, y_um) and check it got there; the distance, um."""
        core, stage, tolerance_um = self.core, self.xy_stage, self.options.mm_xy_tolerance_um
        with device_errors(stage):
            from_x_um, from_y_um = core.getXYPosition(stage)
            core.setXYPosition(stage, x_um, y_um)
            core.waitForDevice(stage)
            at_x_um, at_y_um = core.getXYPosition(stage)
        if abs(at_x_um - x_um) > tolerance_um or abs(at_y_um - y_um) > tolerance_um:
            raise TargetNotReachedError(
                stage,
                f"stopped at ({at_x_um:.3f}, {at_y_um:.3f}) um, sent to ({x_um:.3f}, "
                f"{y_um:.3f}) um (tolerance {tolerance_um} um)",
            )
        return math.hypot(x_um - from_x_um, y_um - from_y_um)

    def _move_z(self, z_um: float) -> None:
        """Move the focus device to `z_um` and check it got there."""
        core, focus, tolerance_um = self.core, self.focus, self.options.mm_z_tolerance_um
        with device_errors(focus):
            core.setPosition(focus, z_um)
            core.waitForDevice(focus)
            at_um = core.getPosition(focus)
        if abs(at_um - z_um) > tolerance_um:
            raise TargetNotReachedError(
                focus,
                f"stopped at z {at_um:.3f} um, sent to {z_um:.3f} um (tolerance {tolerance_um} um)",
            )

    def acquire(self, plan: StackPlan, out: Callable[[int], np.ndarray]) -> Frames:
        if not isinstance(plan, MMCorePlan):
            raise TypeError(f"not a plan of the MMCore backend: {type(plan).__name__}")
        return self._sequence(plan, out) if plan.sequenced else self._snaps(plan, out)

    def _snaps(self, plan: MMCorePlan, out: Callable[[int], np.ndarray]) -> Frames:
        """A focus move, a wait and a snap per frame."""
        with self._stack(plan.exposure_s):
            for index, z_um in enumerate(plan.z_um):
                self._move_z(float(z_um))
                self._snap(plan.exposure_s)
                with device_errors(self.camera, image=True):
                    image = self.core.getImage()
                yield self._frame(image, out(index))

    def _snap(self, exposure_s: float) -> None:
        """Snap an image, waiting no longer than its exposure and the timeout."""
        self._snapping = self._snapper.submit(self.core.snapImage)
        wait_s = exposure_s + self.options.mm_timeout_s
        try:
            failure = self._snapping.exception(timeout=wait_s)
        except TimeoutError:  # the snap's own errors are not raised here, only returned
            raise DeviceTimeoutError(
                self.camera, f"no image {wait_s:.1f} s after the snap began"
            ) from None
        if failure is not None:
            with device_errors(self.camera):
                raise failure

    def _sequence(self, plan: MMCorePlan, out: Callable[[int], np.ndarray]) -> Frames:
        """The focus device's sequence of positions, stepped through on the camera's
        triggers while the camera streams `plan.n_frames` images."""
        core, focus, camera = self.core, self.focus, self.camera
        n_frames = plan.n_frames
        with self._stack(plan.exposure_s):
            with device_errors(focus):
                core.loadStageSequence(focus, [float(z_um) for z_um in plan.z_um])
                core.startStageSequence(focus)
            try:
                with device_errors(camera):
                    core.startSequenceAcquisition(camera, n_frames, 0.0, True)
                deadline_s = (
                    time.perf_counter() + plan.timing.exposure_s + self.options.mm_timeout_s
                )
                for index in range(n_frames):
                    image = self._next_image(index, n_frames, deadline_s)
                    yield self._frame(image, out(index))
            finally:  # also when the consumer stops early or a frame failed
                with device_errors(camera):
                    if core.isSequenceRunning(camera):
                        core.stopSequenceAcquisition(camera)
                with device_errors(focus):
                    core.stopStageSequence(focus)

    def _next_image(self, index: int, n_frames: int, deadline_s: float) -> np.ndarray:
        """Image `index` of a sequence of `n_frames`, waited for until `deadline_s`
        (perf_counter): NoImageError when the sequence ended without it."""
        core, camera = self.core, self.camera
        while True:
            with device_errors(camera, image=True):
                running = core.isSequenceRunning(camera)  # before the count: no image missed
                if core.getRemainingImageCount() > 0:
                    return core.popNextImage()
            if not running:
                raise NoImageError(camera, f"the sequence ended after {index} of {n_frames} frames")
            if time.perf_counter() > deadline_s:
                raise DeviceTimeoutError(
                    camera, f"{index} of {n_frames} frames by the sequence's deadline"
                )
            time.sleep(POLL_S)

    @contextmanager
    def _stack(self, exposure_s: float) -> Iterator[None]:
        """The camera at `exposure_s`, and the shutter open for the whole stack where the
        core would open and close it for every image (a real shutter takes tens of ms)."""
        core = self.core
        with device_errors(self.camera):
            core.setExposure(self.camera, exposure_s * 1000.0)
        shutter = core.getShutterDevice()
        if not (shutter and core.getAutoShutter()):
            yield
            return
        with device_errors(shutter):
            core.setShutterOpen(shutter, True)
            core.setAutoShutter(False)
        try:
            yield
        finally:
            with device_errors(shutter):
                core.setAutoShutter(True)
                core.setShutterOpen(shutter, False)

    def _frame(self, image: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """`frame` ((height, width, channels)) holding the camera's `image`."""
        if image.size == 0:
            raise NoImageError(self.camera, "an empty image")
        if image.dtype != frame.dtype or image.size != frame.size:
            raise DeviceError(
                self.camera,
                f"an image of {image.shape} {image.dtype} for frames of {frame.shape} "
                f"{frame.dtype}: its format changed since the instrument opened",
            )
        frame[...] = image.reshape(frame.shape)
        return frame

    def close(self) -> None:
        self._snapper.shutdown(wait=False, cancel_futures=True)
        if self._snapping is not None:  # a snap that timed out: unload after it, if it ends
            wait([self._snapping], timeout=self.options.mm_timeout_s)
        release_core(self.core)
