"""The scan as a plan: a generator of steps, with no I/O (in the spirit of Bluesky).

`scan_plan(request)` yields the steps of one slide scan and receives each step's
result back (`plan.send(result)`); the engine (`engine.py`) executes them against
the real services, with timeouts and retries. Kept apart like this, the scan
logic (what to ask, what to do with each answer, which frame becomes the
tile's image) is tested against fake results, and the engine only moves
messages.

The loop (docs/scheduler.md):

1. `DescribeSlide`: the slide's tile grid and the objective's depth of field,
   from the instrument;
2. `CreateOrResumeSlide`: a new slide at the estimator (its prior map, if any, uploaded
   as a file: `prior_upload`), or the one a previous run of this scan created (a
   restarted scheduler resumes; the estimator's `/next` says where);
3. until the estimator says `done`: `AskNext`, `Acquire` the z-stack it names,
   `AwaitFocus` for the focus service's result of that stack (not when the
   acquisition only images the tile), `KeepTile` the frame nearest the measured
   focus (the prediction when there is none) as the tile's image for now,
   `PostMeasurement`, and once the tile's estimate is final (the outcome has a
   posterior) `KeepTile` again if another acquired frame of the tile is nearer
   the posterior: that frame is the tile's image (the strategy's `z_used_um`);
   where the outcome names several frames to keep (`planes_um`: one frame is too
   unsure to be in focus), `KeepPlanes` keeps them all beside it. The frames they
   need come first, as an image-only acquisition of purpose `planes`. A revisit
   (purpose `revisit`: a measured tile again, for the drift in time) is acquired,
   measured and posted, and the tile keeps its image; a laser reading (purpose `laser`)
   is `ReadLaser`, posted as the acquisition's measurement. With `ScanRequest.realign` (a
   second pass), each final image is compared with the first pass's (`MatchTile`); once
   the pass's lateral offset is known, the tiles imaged before are taken again at it
   (`Retake`, one frame at their image's z), and every acquisition after goes there. A
   tile imaged with one frame at its prediction (no measurement) is compared with the
   first pass's image of it first (`CompareFrame`): a frame less sharp than
   `Realign.min_sharpness_ratio` of it is posted out of focus
   (`Measurement.frame_out_of_focus`), and the estimator then asks for a stack of the tile.

With `ScanRequest.phase` (``focustrack scan --phase``), once a tile's image is final
(`KeepTile` at the posterior), `AcquirePhase` takes a short phase stack of the tile
centred on the z of that image, for the phase service, and keeps its phase beside the
tile's image (a tile whose phase does not come is reported without it); a tile found empty
(glass, plasma alone) takes none. A tile imaged with one frame at its prediction is then
`AwaitFocus`ed too, as a look (the focus service reads a frame alone as one: empty or
not), so that glass the scan did not measure takes no phase stack either. At the end,
`TilesWithoutPhase` names the tiles an earlier run of a resumed scan left without phase
(killed before their results came), and each gets its phase stack then.

An edge peak or a flat curve is posted as it is; the estimator then asks for
another stack of the same tile, so a retry is just the next `AskNext`. A focus
result that does not come is a lost stack: the same acquisition is made again,
up to `ScanRequest.focus_attempts` times, and then the scan stops with
`FocusUnavailableError`.
"""

from __future__ import annotations

import dataclasses
import io
import math
from collections.abc import Callable, Generator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from focustrack_client import models as api
from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRange,
    ZRangePolicy,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api
from focustrack_core.rest.to_domain import default_policy
from focustrack_core.v1 import focus_pb2
from focustrack_core.wire import keys
from focustrack_scheduler.focus_check import out_of_focus
from focustrack_scheduler.realign import Realign

#: Wire sequence numbers of phase stacks start here (plus the tile's row-major index), far
#: above the estimator's acquisition indices, so the instrument keeps them apart.
PHASE_SEQUENCE_BASE = 1 << 40
#: Wire sequence numbers of tiles taken again at a second pass's lateral offset (`Retake`),
#: likewise.
RETAKE_SEQUENCE_BASE = 1 << 41


#: The least reach of a phase stack either side of its centre, in depths of field of the
#: objective (`PhaseStacks.too_close_to_focus`): the default, 11 planes half a depth of
#: field apart, reaches 2.5; 2 planes at that step, 0.25, still give a phase; 0.005 um
#: either side (a step of 0.001 um) gave a spread of 0.02 rad where the cells have 0.5.
MIN_PHASE_REACH_DOF = 0.2


@dataclass(frozen=True)
class PhaseStacks:
    """The phase stack of each tile: `planes` frames `step_um` apart, centred on the z the
    tile is imaged at; `step_um` None: half the objective's depth of field (the instrument's
    info)."""

    planes: int
    step_um: float | None = None

    def __post_init__(self) -> None:
        if self.planes < 2:
            raise ValueError(f"a phase stack needs at least 2 planes, got {self.planes}")
        if self.step_um is not None and not self.step_um > 0:
            raise ValueError(f"the phase stack's step must be positive, got {self.step_um} um")

    def z_range(self, center_um: float, dof_um: float) -> ZRange:
        """The stack's frames around `center_um` on an objective of depth of field `dof_um`."""
        step_um = self.step_um if self.step_um is not None else dof_um / 2.0
        return ZRange.centred(center_um, self.planes, step_um)

    def too_close_to_focus(self, dof_um: float) -> bool:
        """Whether the stack reaches less than MIN_PHASE_REACH_DOF depths of field either
        side of its centre: nearer focus a plane shows little phase contrast, and the phase
        comes out flat and noisy (the service takes the stack all the same)."""
        z = self.z_range(0.0, dof_um)
        return (z.n_frames - 1) / 2.0 * z.step_um < MIN_PHASE_REACH_DOF * dof_um


@dataclass(frozen=True)
class ScanRequest:
    """What to scan and how: the instrument's slide, the strategy and what is known before.

    `start_z_um` and `start_sigma_um` are the prior height and its std (um) before the
    first tile; `noise_sigma_um` is the std the estimator assumes for a best-focus
    measurement that comes without its own sigma, and sizes the first stacks; the focus
    service's own sigma travels with every measurement. `focus_attempts` is how often one
    stack is acquired before the focus service counts as gone. Their defaults are the
    scan's settings' (`settings.ScanOptions.request`).
    """

    instrument: str
    slide: str
    strategy: str
    start_z_um: float
    start_sigma_um: float
    noise_sigma_um: float
    focus_attempts: int
    params: Mapping[str, Any] = field(default_factory=dict)
    policy: ZRangePolicy = field(default_factory=default_policy)
    resume_slide_id: str | None = None  # the estimator slide of a previous run of this scan
    phase: PhaseStacks | None = None  # a phase stack of every tile (None: none)
    realign: Realign | None = None  # a second pass placed where the first's tiles were

    def __post_init__(self) -> None:
        keys.check_name(self.instrument, "instrument")
        keys.check_name(self.slide, "slide")
        if self.focus_attempts < 1:
            raise ValueError(f"focus_attempts must be at least 1, got {self.focus_attempts}")


@dataclass(frozen=True)
class StageLimits:
    """What the instrument's stage and camera allow a stack: frames within z_min_um..z_max_um
    (its travel, um) and at most `max_frames` of them. None: not stated (an instrument whose
    info predates them), no limit."""

    z_min_um: float | None = None
    z_max_um: float | None = None
    max_frames: int | None = None

    def fit(self, z: ZRange) -> ZRange:
        """`z` cut to `max_frames` (about its centre) and moved inside the travel, frames and
        step unchanged; a stack longer than the travel keeps the frames that fit, from the
        bottom. The instrument refuses a stack that reaches beyond either (Z_OUT_OF_RANGE,
        TOO_MANY_FRAMES), while a stack at the limit still finds a focus near it (or
        flags the edge, and the estimator's retries are bounded)."""
        n_frames = z.n_frames if self.max_frames is None else min(z.n_frames, self.max_frames)
        low_um = z.low_um + (z.n_frames - n_frames) / 2.0 * z.step_um
        if self.z_min_um is None or self.z_max_um is None:
            return ZRange(low_um, z.step_um, n_frames)
        span_um = self.z_max_um - self.z_min_um
        n_frames = min(n_frames, 1 + math.floor(span_um / z.step_um))
        low_um = max(min(low_um, self.z_max_um - (n_frames - 1) * z.step_um), self.z_min_um)
        # Rounding may leave the top frame a hair above the travel, which the instrument
        # refuses like any other frame beyond it.
        while low_um + (n_frames - 1) * z.step_um > self.z_max_um:
            if low_um > self.z_min_um:
                low_um = max(math.nextafter(low_um, -math.inf), self.z_min_um)
            else:
                n_frames -= 1
        return ZRange(low_um, z.step_um, n_frames)

    def limit_policy(self, policy: ZRangePolicy) -> ZRangePolicy:
        """`policy` with no stack larger than the instrument takes (ValueError, the policy's
        own, when it takes fewer than the two frames a focus curve needs: the engine refuses
        such an instrument first)."""
        if self.max_frames is None or policy.max_frames <= self.max_frames:
            return policy
        return dataclasses.replace(
            policy,
            max_frames=self.max_frames,
            min_frames=min(policy.min_frames, self.max_frames),
        )


@dataclass(frozen=True)
class SlideGeometry:
    """What the instrument says about a slide: its tile grid, the depth of field (um), what
    its stage and camera allow a stack, and whether it has a laser (reflection) autofocus
    (None: not stated, an instrument whose info predates it)."""

    grid: ScanGrid
    dof_um: float
    stage: StageLimits = StageLimits()
    laser: bool | None = None


# --- Steps: each is a request to the engine; the comment says what it sends back. ---


@dataclass(frozen=True)
class DescribeSlide:
    """-> SlideGeometry of `slide` on `instrument`, whose stage must take `phase`'s stacks
    (None: no phase)."""

    instrument: str
    slide: str
    phase: PhaseStacks | None = None


@dataclass(frozen=True)
class CreateOrResumeSlide:
    """-> the estimator's slide id: `slide_id` if given (resume), else a new slide of `config`."""

    config: api.SlideCreate
    slide_id: str | None


@dataclass(frozen=True)
class AskNext:
    """-> the pending Acquisition of the estimator slide, or None when the scan is done."""

    slide_id: str


@dataclass(frozen=True)
class Acquire:
    """-> the z (um) of every frame of the stack, once the instrument has published them.

    `attempt` counts from 1; a later attempt repeats a stack whose focus result was lost.
    `asked` is the estimator's z-range where the stage's limits moved or cut it
    (`StageLimits.fit`; the acquisition holds the stack as taken), None where they did not.
    """

    slide: str
    acquisition: Acquisition
    attempt: int = 1
    asked: ZRange | None = None


@dataclass(frozen=True)
class AwaitFocus:
    """-> the focus service's FocusResult for the acquisition's stack, or None on timeout.

    `look_only`: the stack is a frame only imaged, awaited for its look (empty or not);
    None leaves that unknown, where a stack's None has it acquired again.
    """

    slide: str
    acquisition: Acquisition
    look_only: bool = False


@dataclass(frozen=True)
class PostMeasurement:
    """-> the Outcome of posting `measurement` for `acquisition` to the estimator."""

    slide_id: str
    acquisition: Acquisition
    measurement: Measurement


@dataclass(frozen=True)
class ReadLaser:
    """-> the Measurement of a laser reading (purpose laser) of `acquisition`'s tile of
    `slide`: the coverslip's height with the sensor's sigma (`laser.read_laser`)."""

    slide: str
    acquisition: Acquisition


@dataclass(frozen=True)
class Frame:
    """One acquired frame of the tile being scanned."""

    sequence: int
    index: int
    z_um: float


@dataclass(frozen=True)
class KeepTile:
    """-> None. Frame `frame` of the stack of acquisition `sequence` becomes tile (row, col)."""

    row: int
    col: int
    sequence: int
    frame: int
    z_um: float


@dataclass(frozen=True)
class KeepPlanes:
    """-> None. The frames `planes` of tile (row, col), ascending in z, are kept besides its
    image: where one frame is too unsure to be in focus, one of these is (`Outcome.planes_um`)."""

    row: int
    col: int
    planes: tuple[Frame, ...]


@dataclass(frozen=True)
class AcquirePhase:
    """-> None. A phase stack of tile (row, col) at `z`, for the phase service to
    reconstruct at `reference_z_um` (the z of the tile's image), under wire sequence
    `sequence`; its result is kept beside the tile's image when it comes (the engine may
    go on to the next tiles meanwhile, and awaits it before the scan ends)."""

    slide: str
    row: int
    col: int
    z: ZRange
    reference_z_um: float
    sequence: int
    asked: ZRange | None = None  # the stack --phase-planes asks, where the stage cut it


@dataclass(frozen=True)
class TilesWithoutPhase:
    """-> the tiles with an image but no phase, (row, col, z um of the image) each, once the
    phase results still to come have come: a resumed scan's tiles whose phase stack an
    earlier run never took, or never heard of again (it was stopped first). A tile found
    empty is none of them: it takes no phase stack."""


@dataclass(frozen=True)
class MatchTile:
    """-> the tiles to take again, (row, col, z um) each. The tile's image (`image`: the frame
    its last `KeepTile` kept) is final: compared with the first pass's, it may make the
    pass's lateral offset known (`realign.LateralPlacement`), and then the tiles imaged
    before it are taken again at that offset."""

    image: KeepTile


@dataclass(frozen=True)
class CompareFrame:
    """-> the sharpness of the tile's frame kept by `image` over the first pass's image of
    the tile (`realign.LateralPlacement.sharpness_ratio`), None where it cannot be
    compared."""

    image: KeepTile


@dataclass(frozen=True)
class Retake:
    """-> None. One frame of tile (row, col) of `slide` at `z_um`, at the pass's lateral
    offset, under wire sequence `sequence`: it becomes the tile's image."""

    slide: str
    row: int
    col: int
    z_um: float
    sequence: int


Step = (
    DescribeSlide
    | CreateOrResumeSlide
    | AskNext
    | Acquire
    | AwaitFocus
    | PostMeasurement
    | KeepTile
    | KeepPlanes
    | AcquirePhase
    | TilesWithoutPhase
    | ReadLaser
    | MatchTile
    | CompareFrame
    | Retake
)
Plan = Generator[Step, Any, str]


def execute(plan: Plan, answer: Callable[[Step], Any]) -> str:
    """Run `plan` to its end, sending each step `answer`'s result for it; the plan's return
    value (the estimator's slide id). The engine answers with the services; tests with
    stand-ins."""
    result: Any = None
    try:
        while True:
            result = answer(plan.send(result))
    except StopIteration as finished:
        return finished.value


class FocusUnavailableError(RuntimeError):
    """No focus result came for a stack, however often it was acquired."""


def slide_config(request: ScanRequest, geometry: SlideGeometry) -> api.SlideCreate:
    """The estimator slide to create: the request's strategy on the instrument's grid and DOF."""
    settings = SlideSettings(
        grid=geometry.grid,
        start_z_um=request.start_z_um,
        start_sigma_um=request.start_sigma_um,
        dof_um=geometry.dof_um,
        noise_sigma_um=request.noise_sigma_um,
        policy=geometry.stage.limit_policy(request.policy),
    )
    return to_api.slide_create(request.strategy, settings, request.params)


def prior_upload(config: api.SlideCreate) -> tuple[api.SlideCreate, bytes | None]:
    """`config` without its prior map, and that map as the .npy file the estimator takes
    after creation (`PUT /v1/slides/{id}/prior`); None and `config` itself when it has none.

    A map (kf-rescan's `prior_map_um`, rows x cols heights, with `prior_map_sigma_um`
    when those are a map too) makes a large JSON body, over the estimator's limit for a
    creation from about 40 x 40 tiles; as an .npy file it has a limit of its own. One
    sigma for every tile stays a parameter; a map that does not fit the grid stays too,
    for the estimator to refuse in its own words.
    """
    params = dict(config.params)
    map_um = params.get(api.PRIOR_MAP_PARAM)
    rows, cols = config.grid.rows, config.grid.cols
    if not isinstance(map_um, list) or len(map_um) != rows * cols:
        return config, None
    layers = [params.pop(api.PRIOR_MAP_PARAM)]
    sigma_um = params.get(api.PRIOR_SIGMA_PARAM)
    if isinstance(sigma_um, list) and len(sigma_um) == len(map_um):
        layers.append(params.pop(api.PRIOR_SIGMA_PARAM))
    stack = np.asarray(layers, dtype=np.float64).reshape(len(layers), rows, cols)
    npy = io.BytesIO()
    np.save(npy, stack if len(layers) == 2 else stack[0])
    return config.model_copy(update={"params": params}), npy.getvalue()


def measurement_of(result: focus_pb2.FocusResult) -> Measurement:
    """The measurement a focus result reports.

    No best focus (a flat curve, or a stack the service could not read, or a z that is
    no height: not finite, or beyond the API's bounds) is a measurement without z, which
    the estimator answers with another stack. Flags this version does not know are
    dropped; a sigma that is not a positive finite number is left for the estimator's
    default, and one outside the API's bounds is taken at the nearer (a focus service
    that states a picometre must not end the scan).
    """
    flags = frozenset(
        flag for value in result.flags if (flag := FocusFlag.of_proto(value)) is not None
    )
    if (
        result.HasField("error")
        or not result.HasField("best_z_um")
        or not to_api.is_height(result.best_z_um)
    ):
        return Measurement(z_um=None, flags=flags)
    sigma_um = to_api.sigma_within_bounds(result.sigma_um) if result.HasField("sigma_um") else None
    runner_up_um = result.runner_up_z_um if result.HasField("runner_up_z_um") else None
    if runner_up_um is not None and not to_api.is_height(runner_up_um):
        runner_up_um = None
    probability = result.chosen_probability if result.HasField("chosen_probability") else None
    if probability is not None and not 0.0 <= probability <= 1.0:
        probability = None
    return Measurement(result.best_z_um, sigma_um, flags, runner_up_um, probability)


def nearest_frame(frames: list[Frame], z_um: float) -> Frame:
    """The frame nearest `z_um` (the earliest on a tie)."""
    if not frames:
        raise ValueError("no frame has been acquired on this tile")
    return min(frames, key=lambda frame: abs(frame.z_um - z_um))


def _acquire_and_measure(
    request: ScanRequest, acquisition: Acquisition, asked: ZRange | None
) -> Generator[Step, Any, tuple[Measurement, tuple[float, ...]]]:
    """Acquire the stack and read its focus; (measurement, z of its frames)."""
    for attempt in range(1, request.focus_attempts + 1):
        z_um = yield Acquire(request.slide, acquisition, attempt, asked)
        if not acquisition.measure:  # only image the tile: no focus is expected
            return (yield from _look_at_image(request, acquisition)), z_um
        result = yield AwaitFocus(request.slide, acquisition)
        if result is not None:
            return measurement_of(result), z_um
    raise FocusUnavailableError(
        f"no focus result on {keys.focus_key(request.slide, acquisition.row, acquisition.col)} "
        f"for acquisition {acquisition.index} after {request.focus_attempts} attempt(s): is "
        f"the focus service running and subscribed to {keys.zframe_pattern(request.slide)}?"
    )


def _look_at_image(
    request: ScanRequest, acquisition: Acquisition
) -> Generator[Step, Any, Measurement]:
    """What a frame only imaged measured: nothing, except on a phase scan the look's flags
    (the focus service reads a frame alone as a look), so that a tile of glass imaged at a
    sure prediction is known empty and takes no phase stack. A look that does not come
    flags nothing: the phase stack is taken."""
    if request.phase is None or acquisition.purpose is not Purpose.SCAN:
        return Measurement(z_um=None)
    result = yield AwaitFocus(request.slide, acquisition, look_only=True)
    return Measurement(
        z_um=None, flags=frozenset() if result is None else measurement_of(result).flags
    )


def scan_plan(request: ScanRequest) -> Plan:
    """The steps of one slide scan; returns the estimator's slide id when the scan is done."""
    geometry = yield DescribeSlide(request.instrument, request.slide, request.phase)
    slide_id = yield CreateOrResumeSlide(slide_config(request, geometry), request.resume_slide_id)
    tile: tuple[int, int] | None = None
    frames: list[Frame] = []  # every frame acquired on `tile` so far
    phased: set[int] = set()  # the tiles (row-major index) whose phase stack was taken
    while (asked := (yield AskNext(slide_id))) is not None:
        acquisition, asked_z = asked, None
        if (fitted := geometry.stage.fit(asked.z)) != asked.z:
            acquisition, asked_z = dataclasses.replace(asked, z=fitted), asked.z
        if acquisition.purpose is Purpose.REVISIT:  # a measured tile again, for the drift:
            measurement, _ = yield from _acquire_and_measure(request, acquisition, asked_z)
            yield PostMeasurement(slide_id, acquisition, measurement)  # its image stays
            continue
        if acquisition.purpose is Purpose.LASER:  # a reading of the coverslip: no frame
            reading = yield ReadLaser(request.slide, acquisition)
            yield PostMeasurement(slide_id, acquisition, reading)
            continue
        if (acquisition.row, acquisition.col) != tile:
            tile, frames = (acquisition.row, acquisition.col), []
        measurement, z_um = yield from _acquire_and_measure(request, acquisition, asked_z)
        frames += [Frame(acquisition.index, index, z) for index, z in enumerate(z_um)]
        # Keep an image before posting: a scheduler killed right after the post (the
        # estimator has moved on) still leaves this tile with its best guess.
        kept = nearest_frame(frames, _best_guess_um(acquisition, measurement))
        keep = KeepTile(acquisition.row, acquisition.col, kept.sequence, kept.index, kept.z_um)
        yield keep
        if _checked(request, acquisition):
            ratio = yield CompareFrame(keep)
            assert request.realign is not None  # _checked
            if ratio is not None and out_of_focus(ratio, request.realign.min_sharpness_ratio):
                measurement = dataclasses.replace(measurement, frame_out_of_focus=True)
        outcome: Outcome = yield PostMeasurement(slide_id, acquisition, measurement)
        if outcome.posterior_um is not None and math.isfinite(outcome.posterior_um):
            # The tile's estimate is final: its image is the frame nearest it (the frame
            # the strategy reports as `z_used_um`).
            final = nearest_frame(frames, outcome.posterior_um)
            if final != kept:
                yield KeepTile(
                    acquisition.row, acquisition.col, final.sequence, final.index, final.z_um
                )
            if outcome.planes_um:
                planes = tuple(nearest_frame(frames, z_um) for z_um in outcome.planes_um)
                yield KeepPlanes(acquisition.row, acquisition.col, planes)
            tile_index = acquisition.row * geometry.grid.cols + acquisition.col
            if request.realign is not None and acquisition.purpose is not Purpose.SURVEY:
                image = KeepTile(
                    acquisition.row, acquisition.col, final.sequence, final.index, final.z_um
                )
                again = yield MatchTile(image)
                for row, col, z_um in again:
                    sequence = RETAKE_SEQUENCE_BASE + row * geometry.grid.cols + col
                    yield Retake(request.slide, row, col, z_um, sequence)
            # A tile with nothing in view (`empty`: glass, plasma alone) has no phase to
            # reconstruct: its phase stack would be that many frames of glass.
            if (
                request.phase is not None
                and acquisition.purpose is not Purpose.SURVEY
                and FocusFlag.EMPTY not in measurement.flags
                and tile_index not in phased
            ):
                phased.add(tile_index)
                yield _phase_stack(request, geometry, acquisition.row, acquisition.col, final.z_um)
    if request.phase is not None:  # what an earlier run of this scan left without phase
        for row, col, z_um in (yield TilesWithoutPhase()):
            if (tile_index := row * geometry.grid.cols + col) not in phased:
                phased.add(tile_index)
                yield _phase_stack(request, geometry, row, col, z_um)
    return slide_id


def _phase_stack(
    request: ScanRequest, geometry: SlideGeometry, row: int, col: int, z_um: float
) -> AcquirePhase:
    """The phase stack of tile (row, col), centred on its image's `z_um`, within the stage
    (`asked` says what it was before the stage's travel or frame limit cut it)."""
    assert request.phase is not None
    asked = request.phase.z_range(z_um, geometry.dof_um)
    z = geometry.stage.fit(asked)
    sequence = PHASE_SEQUENCE_BASE + row * geometry.grid.cols + col
    return AcquirePhase(request.slide, row, col, z, z_um, sequence, None if z == asked else asked)


def _checked(request: ScanRequest, acquisition: Acquisition) -> bool:
    """Whether `acquisition`'s frame is compared with the first pass's image: a tile imaged
    once at its prediction, on a second pass that checks (`focus_check`)."""
    return (
        request.realign is not None
        and request.realign.min_sharpness_ratio > 0
        and not acquisition.measure
        and acquisition.purpose is Purpose.SCAN
    )


def _best_guess_um(acquisition: Acquisition, measurement: Measurement) -> float:
    """Where the tile's focus is before the estimator has answered: measured, else predicted."""
    if measurement.z_um is not None:
        return measurement.z_um
    if acquisition.predicted_um is not None and math.isfinite(acquisition.predicted_um):
        return acquisition.predicted_um
    return acquisition.z.center_um
