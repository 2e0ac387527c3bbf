"""The instrument seam: what the Zenoh shell (`service.py`) needs from a microscope, no more.

A backend is any object with the methods of `Instrument`: the simulator
(`simulated.SimulatedInstrument`) is one; a real microscope behind Micro-Manager is
another. The shell calls them like this, for each acquisition, one at a time:

1. `Instrument.plan` checks a request (slide, tile, z range, frame count, exposure)
   and commits the instrument to it, or raises `AcquisitionRefusedError` with a
   `Refusal` and the offending field. The `StackPlan` it returns says where the stage
   goes (the tile's stage x, y and the z of every frame), what the frames will be
   (`FrameFormat`) and what the stack costs (`StackTiming`).
2. `Instrument.acquire` takes the planned frames, frame k into the buffer `out(k)` the
   shell hands it, and yields each buffer, in z order, as soon as its frame exists.
   Stage moves happen within (1) and (2): the shell never moves the stage by itself.

A request has a `Purpose`: a FOCUS stack (the focus service's) or a PHASE stack (the
phase service's, reconstructed at the request's `reference_z_um`). The plan echoes both,
with the `ImagingConditions` a reader of the frames needs (wavelength, condenser and
objective NA, the camera's gain and offset), which go into every stack's header.

`Instrument.describe` (the info queryable), `TruthSource.truth` and
`PhaseTruthSource.phase_truth` (evaluation only) are called from Zenoh's threads, also
while a stack is being acquired. A device that fails raises one of the `DeviceError`s;
the shell turns every `InstrumentError` into an error reply with its own code (and
anything else into an INTERNAL one) and keeps serving. A backend bounds its waits on
devices: a device that does not answer is a `DeviceTimeoutError`, not a call that never
returns.

Units: um for x, y, z and lengths; s for times. Frames are numpy arrays
(height, width, channels), C-ordered.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, runtime_checkable

import numpy as np

from focustrack_core.geometry import ScanGrid


class Refusal(StrEnum):
    """Why a request cannot be acquired."""

    MALFORMED = "malformed_request"
    UNKNOWN_SLIDE = "unknown_slide"
    TILE_OUTSIDE_SLIDE = "tile_outside_slide"
    Z_OUT_OF_RANGE = "z_out_of_range"
    TOO_MANY_FRAMES = "too_many_frames"


class InstrumentError(Exception):
    """What an instrument raises on purpose: a refused request or a failed device."""


class AcquisitionRefusedError(InstrumentError, ValueError):
    """A request the instrument will not carry out; `reason` and `field` say why."""

    def __init__(self, reason: Refusal, message: str, field: str = "") -> None:
        super().__init__(message)
        self.reason = reason
        self.field = field


class DeviceError(InstrumentError):
    """A device of the instrument failed while carrying out an accepted request (its
    driver reported an error). `device` names it (a Micro-Manager label, "camera", ...)."""

    def __init__(self, device: str, message: str) -> None:
        super().__init__(f"{device}: {message}")
        self.device = device


class DeviceTimeoutError(DeviceError):
    """A device did not finish in time (a move, an exposure, a readout)."""


class TargetNotReachedError(DeviceError):
    """The stage stopped away from the position it was sent to."""


class NoImageError(DeviceError):
    """The camera delivered no image for a frame."""


@dataclass(frozen=True)
class FrameFormat:
    """The pixels of one frame: an array `shape` (height, width, channels) of `dtype`,
    one channel per letter of `channel_order` ("RGB"), values below 2**bit_depth."""

    height: int
    width: int
    channel_order: str
    dtype: np.dtype
    bit_depth: int

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.height, self.width, len(self.channel_order))


@dataclass(frozen=True)
class SlideLayout:
    """A slide the instrument can scan: its name and its tile grid (tile (row, col) is
    centred at stage `grid.stage_xy_um(row, col)`, um)."""

    name: str
    grid: ScanGrid


@dataclass(frozen=True)
class OpticsInfo:
    """The objective and camera as the specimen sees them (lengths in um)."""

    pixel_size_um: float  # a camera pixel in the specimen plane
    numerical_aperture: float
    magnification: float
    wavelength_um: float  # the reference wavelength of the depth of field
    refractive_index: float  # of the immersion medium (1.0: air)
    depth_of_field_um: float  # lambda n / NA^2 + n e / (M NA)


def depth_of_field_um(
    wavelength_um: float, refractive_index: float, numerical_aperture: float, pixel_size_um: float
) -> float:
    """The depth of field, um: lambda n / NA^2 (the Rayleigh quarter-wave criterion) plus
    n e / (M NA), one camera pixel e seen through magnification M (e / M: `pixel_size_um`,
    the pixel in the specimen plane)."""
    na, n = numerical_aperture, refractive_index
    return wavelength_um * n / na**2 + n * pixel_size_um / na


@dataclass(frozen=True)
class Description:
    """What an instrument offers, as the info queryable (`InstrumentInfo`) reports it."""

    slides: tuple[SlideLayout, ...]
    frame: FrameFormat
    optics: OpticsInfo
    z_range_um: tuple[float, float]  # (low, high) travel of the focus stage
    max_frames: int  # the largest stack accepted
    default_exposure_s: float  # the exposure of a request that names none
    hardware_sequenced: bool = False  # stacks run as a triggered hardware sequence, not a
    # move and a snap per frame: frames come at the camera's rate

    def __post_init__(self) -> None:
        if not self.slides:
            raise ValueError("an instrument offers at least one slide")


@dataclass(frozen=True)
class StackTiming:
    """Durations of one acquisition in seconds (distance in um)."""

    move_distance_um: float
    move_s: float  # the XY move to the tile, settling included
    z_settle_s: float  # of every frame together
    exposure_s: float  # of every frame together
    readout_s: float  # of every frame together

    @property
    def total_s(self) -> float:
        return self.move_s + self.z_settle_s + self.exposure_s + self.readout_s


class Purpose(StrEnum):
    """What a stack is taken for (the wire's AcquisitionPurpose)."""

    FOCUS = "focus"  # the focus service finds the best focus in it
    PHASE = "phase"  # the phase service reconstructs amplitude and phase at reference_z_um


@dataclass(frozen=True)
class ImagingConditions:
    """How the frames were formed, for a reader that models them (phase retrieval).

    wavelength_um: the illumination's (centre) wavelength, um; 0: unknown.
    condenser_na: the illumination's NA; 0: a coherent point source.
    objective_na: the objective's NA; 0: unknown.
    photons_per_count: the camera's gain, photons (photo-electrons, at a quantum
        efficiency of 1) per count; 0: unknown.
    dark_counts: the camera's offset, the counts of a pixel that receives no light.
    """

    wavelength_um: float = 0.0
    condenser_na: float = 0.0
    objective_na: float = 0.0
    photons_per_count: float = 0.0
    dark_counts: float = 0.0


@dataclass(frozen=True)
class StackRequest:
    """Frames at z_low_um, z_low_um + z_step_um, ... (n_frames of them, um) of tile (row, col)
    of `slide`, each exposed `exposure_s` (None: the instrument's default), for `purpose`;
    a PHASE stack names the objective z to reconstruct at, `reference_z_um`. The stage goes
    `stage_offset_x_um`, `stage_offset_y_um` from the tile's place (a second pass's lateral
    correction, um). Unchecked: the instrument's `plan` refuses what it cannot acquire."""

    slide: str
    row: int
    col: int
    z_low_um: float
    z_step_um: float
    n_frames: int
    exposure_s: float | None = None
    purpose: Purpose = Purpose.FOCUS
    reference_z_um: float = 0.0
    stage_offset_x_um: float = 0.0
    stage_offset_y_um: float = 0.0


@dataclass(frozen=True)
class StackPlan:
    """An accepted acquisition of tile (row, col) of `slide`, before its frames exist.

    z_um (n,): the z of every frame, in acquisition order, um; the stage goes to
    (stage_x_um, stage_y_um). `clock_s` is the instrument's clock, s, when the stack is
    complete (the simulator's simulated clock). `purpose` and `reference_z_um` echo the
    request's; `imaging` says how the frames are formed. A backend may subclass it to
    carry what `acquire` needs besides.
    """

    slide: str
    row: int
    col: int
    stage_x_um: float
    stage_y_um: float
    z_um: np.ndarray
    exposure_s: float  # of each frame
    frame: FrameFormat
    pixel_size_um: float
    timing: StackTiming
    clock_s: float
    # keyword-only, with defaults: a backend's subclass adds fields without defaults
    purpose: Purpose = field(default=Purpose.FOCUS, kw_only=True)
    reference_z_um: float = field(default=0.0, kw_only=True)
    imaging: ImagingConditions = field(default_factory=ImagingConditions, kw_only=True)

    @property
    def n_frames(self) -> int:
        return len(self.z_um)


@dataclass(frozen=True)
class FocusTruth:
    """The ground truth of a slide (evaluation only): the true focus of every tile now,
    (rows, cols) um, drift included; the drift, um; the clock at which they hold, s."""

    best_focus_um: np.ndarray
    drift_um: float
    clock_s: float
    #: a virtual slide's contents, (rows, cols) each (None: a slide of separate fields):
    #: tissue share of the tile's area, whether it is empty glass, the height (um, now,
    #: as best_focus_um) of its coverslip dust and of a fold's upper layer (NaN: none)
    tiles: TileContents | None = None
    #: where the slide lies on the stage against where it lay at the start (x, y), um:
    #: the stage at (x, y) shows the slide's (x - dx, y - dy)
    lateral_offset_um: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class TileContents:
    """What lies in each tile of a virtual slide, (rows, cols) each (see FocusTruth)."""

    tissue_share: np.ndarray
    empty: np.ndarray
    dust_z_um: np.ndarray
    fold_z_um: np.ndarray


@dataclass(frozen=True)
class TilePhase:
    """The true phase of a tile's specimen (evaluation only): phase_rad (height, width)
    float32, radians, over the frame's pixels (`pixel_size_um` each); the specimen's
    true focus height over the tile now, focus_z_um (drift included)."""

    phase_rad: np.ndarray
    pixel_size_um: float
    focus_z_um: float


#: The longest exposure a request may ask for, s.
MAX_EXPOSURE_S = 10.0

#: The farthest a request may send the stage from its tile's place, um (a lateral
#: correction is a few um; more is a mistake, not drift).
MAX_STAGE_OFFSET_UM = 1000.0
#: The finest z step a stack may ask, um: a nanometre, a piezo stage's step (the REST API's
#: least z step too); finer, its frames are at one z and no curve can be read from them.
MIN_Z_STEP_UM = 1e-3


def check_tile(slide: str, row: int, col: int, grids: Mapping[str, ScanGrid]) -> ScanGrid:
    """The grid of `slide`, or AcquisitionRefusedError for an unknown slide (UNKNOWN_SLIDE)
    or a tile (row, col) outside its grid (TILE_OUTSIDE_SLIDE)."""
    if slide not in grids:
        known = ", ".join(sorted(grids))
        raise AcquisitionRefusedError(
            Refusal.UNKNOWN_SLIDE, f"unknown slide {slide!r}; known: {known}", "slide"
        )
    grid = grids[slide]
    if not grid.contains(row, col):
        raise AcquisitionRefusedError(
            Refusal.TILE_OUTSIDE_SLIDE,
            f"tile ({row}, {col}) is outside slide {slide!r} of {grid.rows}x{grid.cols} tiles",
            "row" if not 0 <= row < grid.rows else "col",
        )
    return grid


def check_request(
    request: StackRequest,
    exposure_s: float,
    grids: Mapping[str, ScanGrid],
    z_range_um: tuple[float, float],
    max_frames: int,
) -> ScanGrid:
    """The grid of the slide `request` names, or AcquisitionRefusedError saying what is wrong
    with the request: an unknown slide, a tile outside its grid, too many or too few frames,
    a z or z step that is not finite and positive, frames outside `z_range_um` (low, high),
    an `exposure_s` (the request's, or the instrument's default) outside (0, 10] s, and for
    a PHASE stack a `reference_z_um` that is not finite or outside `z_range_um`, and a
    stage offset that is not finite or beyond `MAX_STAGE_OFFSET_UM`. What every
    instrument refuses alike; a backend checks its own limits besides."""
    grid = check_tile(request.slide, request.row, request.col, grids)
    for name in ("stage_offset_x_um", "stage_offset_y_um"):
        offset_um = getattr(request, name)
        if not (np.isfinite(offset_um) and abs(offset_um) <= MAX_STAGE_OFFSET_UM):
            raise AcquisitionRefusedError(
                Refusal.MALFORMED,
                f"{name} must be finite and at most {MAX_STAGE_OFFSET_UM:g} um, got {offset_um}",
                name,
            )
    n_frames = request.n_frames
    if n_frames > max_frames:
        raise AcquisitionRefusedError(
            Refusal.TOO_MANY_FRAMES,
            f"{n_frames} frames requested; the instrument takes at most {max_frames}",
            "n_frames",
        )
    if n_frames < 1:
        raise AcquisitionRefusedError(
            Refusal.MALFORMED, f"n_frames must be at least 1, got {n_frames}", "n_frames"
        )
    z_low_um, z_step_um = request.z_low_um, request.z_step_um
    if not np.isfinite(z_low_um):
        raise AcquisitionRefusedError(Refusal.MALFORMED, "z_low_um must be finite", "z_low_um")
    if n_frames > 1 and not (np.isfinite(z_step_um) and z_step_um >= MIN_Z_STEP_UM):
        raise AcquisitionRefusedError(
            Refusal.MALFORMED,
            f"z_step_um must be at least {MIN_Z_STEP_UM:g} um for {n_frames} frames, got "
            f"{z_step_um}",
            "z_step_um",
        )
    z_high_um = z_low_um + (n_frames - 1) * z_step_um
    z_low, z_high = z_range_um
    if z_low_um < z_low or z_high_um > z_high:
        raise AcquisitionRefusedError(
            Refusal.Z_OUT_OF_RANGE,
            f"frames span z {z_low_um:.3f}..{z_high_um:.3f} um, outside the stage's travel "
            f"{z_low:.1f}..{z_high:.1f} um",
            "z_low_um",
        )
    if not (np.isfinite(exposure_s) and 0 < exposure_s <= MAX_EXPOSURE_S):
        raise AcquisitionRefusedError(
            Refusal.MALFORMED,
            f"exposure must be in (0, {MAX_EXPOSURE_S:g}] s, got {exposure_s}",
            "exposure_s",
        )
    if request.purpose is Purpose.PHASE:
        reference_z_um = request.reference_z_um
        if not np.isfinite(reference_z_um):
            raise AcquisitionRefusedError(
                Refusal.MALFORMED, "reference_z_um must be finite", "reference_z_um"
            )
        if not z_low <= reference_z_um <= z_high:
            raise AcquisitionRefusedError(
                Refusal.Z_OUT_OF_RANGE,
                f"reference_z_um {reference_z_um:.3f} um is outside the stage's travel "
                f"{z_low:.1f}..{z_high:.1f} um",
                "reference_z_um",
            )
    return grid


#: The frames of a stack as `Instrument.acquire` yields them, (height, width, channels) each.
Frames = Generator[np.ndarray, None, None]


class Instrument(Protocol):
    """A microscope the Zenoh shell can serve (see the module's doc for the call order)."""

    def describe(self) -> Description:
        """The slides, frames, optics and limits of the instrument."""
        ...

    def plan(self, request: StackRequest) -> StackPlan:
        """Accept the stack `request` asks for; the shell acquires the plan next. Raises
        AcquisitionRefusedError (nothing changes) or DeviceError."""
        ...

    def acquire(self, plan: StackPlan, out: Callable[[int], np.ndarray]) -> Frames:
        """The frames of `plan`, in order: frame k is written into `out(k)` (an array of
        `plan.frame.shape` and dtype, which the shell may publish without a copy), which
        is yielded as soon as the frame is complete. Raises DeviceError. A consumer that
        stops early closes the generator: the instrument stops the stack then."""
        ...

    def close(self) -> None:
        """Release the devices (and threads); the instrument is not used afterwards."""
        ...


@runtime_checkable
class TruthSource(Protocol):
    """An instrument that knows the true focus of its slides (the simulator): served on
    ``focustrack/v1/eval/truth/...`` with ``--serve-truth``, for evaluation only."""

    def truth(self, slide: str) -> FocusTruth:
        """The ground truth of `slide` now; AcquisitionRefusedError(UNKNOWN_SLIDE) for a
        slide the instrument does not have."""
        ...


@runtime_checkable
class PhaseTruthSource(Protocol):
    """An instrument that knows the true phase of its specimens (the simulator): served on
    ``focustrack/v1/eval/phase/...`` with ``--serve-truth``, for evaluation only."""

    def phase_truth(self, slide: str, row: int, col: int) -> TilePhase:
        """The true phase of tile (row, col) of `slide`; AcquisitionRefusedError
        (UNKNOWN_SLIDE, TILE_OUTSIDE_SLIDE) for a tile the instrument does not have."""
        ...
