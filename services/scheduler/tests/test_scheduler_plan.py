"""The scan plan against fake step results: pure, no services.

`FakeEstimator` stands in for the estimator and the focus service alike, built from the
plan's own steps: it scans every tile in serpentine order with stacks centred on the last
estimate, retries a tile whose peak lies beyond its stack, and (for the tiles it is told)
asks for an image-only stack and names frames of both stacks to keep (`Outcome.planes_um`),
as the lean strategies do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from focustrack_client import models as api
from focustrack_core.domain import Acquisition, FocusFlag, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api
from focustrack_core.v1 import common_pb2, focus_pb2
from focustrack_scheduler.plan import (
    PHASE_SEQUENCE_BASE,
    RETAKE_SEQUENCE_BASE,
    Acquire,
    AcquirePhase,
    AskNext,
    AwaitFocus,
    CompareFrame,
    CreateOrResumeSlide,
    DescribeSlide,
    FocusUnavailableError,
    KeepPlanes,
    KeepTile,
    MatchTile,
    PhaseStacks,
    PostMeasurement,
    Retake,
    ScanRequest,
    SlideGeometry,
    StageLimits,
    Step,
    TilesWithoutPhase,
    execute,
    measurement_of,
    scan_plan,
)
from focustrack_scheduler.realign import Realign
from focustrack_scheduler.settings import ScanOptions

GEOMETRY = SlideGeometry(ScanGrid(2, 2), dof_um=0.9)
DEFAULTS = ScanOptions.defaults()
REQUEST = DEFAULTS.request("sim", "slide-0", "kf-wiener0")
STEP_UM = 0.5


def drive(request: ScanRequest, answer: Callable[[Step], Any]) -> tuple[list[Step], str]:
    """Run the plan, answering each step with `answer`; the steps and the plan's result."""
    steps: list[Step] = []

    def answer_and_keep(step: Step) -> Any:
        steps.append(step)
        return answer(step)

    return steps, execute(scan_plan(request), answer_and_keep)


def acquisition(
    index: int, row: int, col: int, low_um: float, n: int = 5, measure: bool = True
) -> Acquisition:
    return Acquisition(index, row, col, ZRange(low_um, STEP_UM, n), Purpose.SCAN, measure)


def focus(
    acq: Acquisition, best_z_um: float | None, *flags: int, sigma_um: float = 0.05
) -> focus_pb2.FocusResult:
    result = focus_pb2.FocusResult(
        slide="slide-0", row=acq.row, col=acq.col, sequence=acq.index, flags=list(flags)
    )
    result.z_um.extend(acq.z.z_um().tolist())
    if best_z_um is not None:
        result.best_z_um, result.sigma_um = best_z_um, sigma_um
    return result


class FakeEstimator:
    """The estimator and the focus service of a slide whose focus is `truth_um` (rows, cols).

    Stacks of 5 frames centred on the last estimate (`start_z_um` first); a peak beyond a
    stack comes back as an edge and the tile is taken again past that edge; the estimate
    of a tile is its measured peak. A tile of `planes_tiles` is first answered without a
    final estimate, then given an image-only stack of 3 frames between the first's, and
    keeps the 2 frames of each stack nearest its peak.
    """

    def __init__(
        self, grid: ScanGrid, truth_um: np.ndarray, planes_tiles: frozenset[tuple[int, int]]
    ) -> None:
        self.truth_um = truth_um
        self.planes_tiles = planes_tiles
        self.tiles = iter([(tile.row, tile.col) for tile in grid.serpentine])
        self.estimate_um = 0.0
        self.index = 0
        self.pending: Acquisition | None = None
        self.frames_um: list[float] = []  # every frame of the tile being scanned
        self.outcomes: list[Outcome] = []
        #: what the engine says an earlier run left without phase (row, col, z um)
        self.without_phase: list[tuple[int, int, float]] = []
        #: tiles with nothing in view: their stack is `empty`, and the tile is done with it
        self.empty_tiles: frozenset[tuple[int, int]] = frozenset()

    def _acquisition(self, tile: tuple[int, int], z: ZRange, purpose: Purpose) -> Acquisition:
        self.index += 1
        return Acquisition(self.index, *tile, z, purpose, purpose is not Purpose.PLANES)

    def next(self) -> Acquisition | None:
        if self.pending is None:
            tile = next(self.tiles, None)
            if tile is None:
                return None
            self.frames_um = []
            z = ZRange.centred(self.estimate_um, 5, STEP_UM)
            self.pending = self._acquisition(tile, z, Purpose.SCAN)
        return self.pending

    def focus(self, acq: Acquisition) -> focus_pb2.FocusResult:
        if (acq.row, acq.col) in self.empty_tiles:
            return focus(acq, None, FocusFlag.EMPTY.proto, FocusFlag.FLAT.proto)
        truth_um = float(self.truth_um[acq.row, acq.col])
        if truth_um < acq.z.low_um:
            return focus(acq, None, FocusFlag.EDGE_LOW.proto)
        if truth_um > acq.z.high_um:
            return focus(acq, None, FocusFlag.EDGE_HIGH.proto)
        return focus(acq, truth_um)

    def post(self, acq: Acquisition, measurement: Measurement) -> Outcome:
        tile = (acq.row, acq.col)
        self.frames_um += acq.z.z_um().tolist()
        if measurement.flags & {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH}:
            shift_um = acq.z.n_frames * STEP_UM
            low_um = acq.z.low_um + (
                shift_um if FocusFlag.EDGE_HIGH in measurement.flags else -shift_um
            )
            self.pending = self._acquisition(tile, ZRange(low_um, STEP_UM, 5), Purpose.RETRY)
            return self._outcome(Outcome(*tile, accepted=False))
        if FocusFlag.EMPTY in measurement.flags:  # done: imaged where it was looked at
            self.pending = None
            return self._outcome(Outcome(*tile, accepted=False, posterior_um=self.estimate_um))
        if acq.measure:
            assert measurement.z_um is not None
            self.estimate_um = measurement.z_um
        if tile in self.planes_tiles and acq.measure:  # more frames first: not final yet
            between = ZRange(acq.z.low_um + STEP_UM / 2, STEP_UM, 3)
            self.pending = self._acquisition(tile, between, Purpose.PLANES)
            return self._outcome(Outcome(*tile, accepted=True))
        self.pending = None
        planes_um: tuple[float, ...] = ()
        if tile in self.planes_tiles:
            nearest = sorted(self.frames_um, key=lambda z: abs(z - self.estimate_um))
            planes_um = tuple(sorted(nearest[:4]))
        final = Outcome(
            *tile, accepted=acq.measure, posterior_um=self.estimate_um, planes_um=planes_um
        )
        return self._outcome(final)

    def _outcome(self, outcome: Outcome) -> Outcome:
        self.outcomes.append(outcome)
        return outcome

    def answer(self, geometry: SlideGeometry) -> Callable[[Step], Any]:
        """Answers to the plan's steps on a slide of `geometry`."""

        def answer(step: Step) -> Any:
            match step:
                case DescribeSlide():
                    return geometry
                case CreateOrResumeSlide():
                    return "slide-id"
                case AskNext():
                    return self.next()
                case Acquire():
                    return tuple(step.acquisition.z.z_um())
                case AwaitFocus():
                    return self.focus(step.acquisition)
                case PostMeasurement():
                    return self.post(step.acquisition, step.measurement)
                case KeepTile() | KeepPlanes():
                    return None
                case AcquirePhase():
                    return True
                case TilesWithoutPhase():
                    return self.without_phase

        return answer


def test_every_tile_is_scanned_and_keeps_the_frame_nearest_its_estimate() -> None:
    """The plan against a fake estimator: edges retried, every tile imaged at its estimate."""
    grid = ScanGrid(3, 4)
    truth_um = np.linspace(-3.0, 4.0, grid.n_tiles).reshape(grid.shape)
    request = DEFAULTS.request("sim", "slide-0", "kf-wiener0")
    geometry = SlideGeometry(grid, dof_um=0.9)
    fake = FakeEstimator(grid, truth_um, frozenset())

    steps, slide_id = drive(request, fake.answer(geometry))
    assert slide_id == "slide-id"
    (create,) = [s for s in steps if isinstance(s, CreateOrResumeSlide)]
    assert create.slide_id is None and create.config.grid.rows == 3
    assert create.config.dof_um == 0.9
    assert create.config.noise_sigma_um == DEFAULTS.noise_sigma_um
    acquired = [s.acquisition for s in steps if isinstance(s, Acquire)]
    assert any(a.purpose == Purpose.RETRY for a in acquired)  # some peaks beyond a stack
    last_kept = {(s.row, s.col): s for s in steps if isinstance(s, KeepTile)}
    assert set(last_kept) == {(t.row, t.col) for t in grid.serpentine}
    for (row, col), kept in last_kept.items():
        frames_um = [z for a in acquired if (a.row, a.col) == (row, col) for z in a.z.z_um()]
        nearest_um = min(frames_um, key=lambda z: abs(z - truth_um[row, col]))
        assert kept.z_um == pytest.approx(nearest_um)  # the frame nearest the final estimate
        assert abs(kept.z_um - truth_um[row, col]) <= STEP_UM / 2
    # Every Acquire is answered by exactly one AwaitFocus (all these stacks are measured).
    assert len(acquired) == sum(isinstance(s, AwaitFocus) for s in steps)


def test_with_phase_each_tile_takes_one_phase_stack_centred_on_its_image() -> None:
    """After a tile's image is final (planes and retries included), one phase stack of it,
    centred on the z of that image, half a depth of field between frames by default."""
    grid = ScanGrid(3, 3)
    truth_um = np.random.default_rng(4).normal(0.0, 0.4, grid.shape)
    geometry = SlideGeometry(grid, dof_um=0.9)
    fake = FakeEstimator(grid, truth_um, frozenset({(1, 1)}))
    request = replace(REQUEST, phase=PhaseStacks(planes=11))

    steps, _ = drive(request, fake.answer(geometry))
    phase = [s for s in steps if isinstance(s, AcquirePhase)]
    assert [(s.row, s.col) for s in phase] == [(t.row, t.col) for t in grid.serpentine]
    for step in phase:
        before = steps[: steps.index(step)]
        image = [
            k for k in before if isinstance(k, KeepTile) and (k.row, k.col) == (step.row, step.col)
        ][-1]
        assert step.reference_z_um == image.z_um and step.z.center_um == pytest.approx(image.z_um)
        assert step.z.n_frames == 11 and step.z.step_um == pytest.approx(0.45)
        assert step.sequence == PHASE_SEQUENCE_BASE + step.row * grid.cols + step.col
        later = steps[steps.index(step) + 1 :]  # the tile is done: no more of its stacks
        assert not any(
            isinstance(a, Acquire)
            and (a.acquisition.row, a.acquisition.col) == (step.row, step.col)
            for a in later
        )
    # without it, the same scan takes the same steps and no phase stack (its description
    # of the slide asks for none)
    assert steps[0] == DescribeSlide(REQUEST.instrument, REQUEST.slide, request.phase)
    plain, _ = drive(REQUEST, FakeEstimator(grid, truth_um, frozenset({(1, 1)})).answer(geometry))
    assert plain == [replace(steps[0], phase=None)] + [
        s for s in steps[1:] if not isinstance(s, AcquirePhase | TilesWithoutPhase)
    ]


def test_a_resumed_scan_takes_the_phase_an_earlier_run_left_out_at_its_end() -> None:
    """Tiles an earlier run imaged but left without phase (killed before their results came)
    get their phase stack at the end, centred on their image; a tile this run took a phase
    stack of is not taken twice, and without --phase nothing is asked."""
    grid = ScanGrid(2, 2)
    truth_um = np.zeros(grid.shape)
    geometry = SlideGeometry(grid, dof_um=0.9)
    fake = FakeEstimator(grid, truth_um, frozenset())
    fake.tiles = iter([(1, 0), (1, 1)])  # the earlier run finished row 0
    fake.without_phase = [(0, 0, 0.25), (0, 1, -0.5), (1, 1, 0.0)]  # (1, 1): this run's
    request = replace(REQUEST, phase=PhaseStacks(planes=5))

    steps, _ = drive(request, fake.answer(geometry))
    asked = steps.index(TilesWithoutPhase())
    assert not any(isinstance(s, AskNext | Acquire) for s in steps[asked:])  # at the end
    late = [s for s in steps[asked:] if isinstance(s, AcquirePhase)]
    assert [(s.row, s.col, s.reference_z_um) for s in late] == [(0, 0, 0.25), (0, 1, -0.5)]
    assert late[0].z.center_um == pytest.approx(0.25)
    assert late[1].sequence == PHASE_SEQUENCE_BASE + 1
    phased = [(s.row, s.col) for s in steps if isinstance(s, AcquirePhase)]
    assert sorted(phased) == [(0, 0), (0, 1), (1, 0), (1, 1)]  # each tile once
    plain, _ = drive(REQUEST, FakeEstimator(grid, truth_um, frozenset()).answer(geometry))
    assert TilesWithoutPhase() not in plain


def test_a_tile_found_empty_takes_no_phase_stack_now_or_when_resumed() -> None:
    """A tile with nothing in view (glass, plasma alone) has no phase to reconstruct: it is
    imaged and done, with no phase stack, and what the engine says is left without phase
    (which leaves such tiles out) is all a resumed scan takes at its end."""
    grid = ScanGrid(3, 3)
    truth_um = np.zeros(grid.shape)
    fake = FakeEstimator(grid, truth_um, frozenset())
    fake.empty_tiles = frozenset({(0, 1), (2, 2)})
    fake.without_phase = [(1, 1, 0.0)]  # not this run's: an earlier run's tile
    request = replace(REQUEST, phase=PhaseStacks(planes=5))
    steps, _ = drive(request, fake.answer(SlideGeometry(grid, dof_um=0.9)))
    kept = {(s.row, s.col) for s in steps if isinstance(s, KeepTile)}
    assert kept == {(t.row, t.col) for t in grid.serpentine}  # the empty tiles imaged too
    phased = [(s.row, s.col) for s in steps if isinstance(s, AcquirePhase)]
    assert sorted(phased) == sorted(kept - fake.empty_tiles)  # (1, 1) once


def test_a_phase_stack_cut_by_the_stage_says_what_was_asked() -> None:
    """--phase-planes beyond the camera's frame limit: the stack is cut, and the step says
    what was asked, so the engine warns (the cut was silent)."""
    grid = ScanGrid(1, 2)
    geometry = SlideGeometry(grid, dof_um=0.9, stage=StageLimits(-10.0, 10.0, 4))
    fake = FakeEstimator(grid, np.zeros(grid.shape), frozenset())
    steps, _ = drive(replace(REQUEST, phase=PhaseStacks(planes=9)), fake.answer(geometry))
    phase = [s for s in steps if isinstance(s, AcquirePhase)]
    assert len(phase) == 2
    for step in phase:
        assert step.asked is not None and (step.asked.n_frames, step.z.n_frames) == (9, 4)
    fake = FakeEstimator(grid, np.zeros(grid.shape), frozenset())
    steps, _ = drive(replace(REQUEST, phase=PhaseStacks(planes=3)), fake.answer(geometry))
    phase = [s for s in steps if isinstance(s, AcquirePhase)]
    assert len(phase) == 2 and all(s.asked is None for s in phase)


def test_a_phase_stack_needs_two_planes_and_a_positive_step() -> None:
    assert PhaseStacks(3, 0.2).z_range(1.0, dof_um=0.9).z_um().tolist() == pytest.approx(
        [0.8, 1.0, 1.2]
    )
    with pytest.raises(ValueError, match="at least 2 planes"):
        PhaseStacks(1)
    with pytest.raises(ValueError, match="positive"):
        PhaseStacks(5, 0.0)


@pytest.mark.parametrize(
    ("asked", "limits", "taken"),
    [
        # within the travel and the frame limit: unchanged
        (ZRange(-1.0, 0.5, 5), StageLimits(-10.0, 10.0, 8), ZRange(-1.0, 0.5, 5)),
        # across the top of the travel: moved down, frames kept
        (ZRange(9.0, 0.5, 5), StageLimits(-10.0, 10.0, 8), ZRange(8.0, 0.5, 5)),
        # below the bottom: moved up
        (ZRange(-12.0, 0.5, 5), StageLimits(-10.0, 10.0, 8), ZRange(-10.0, 0.5, 5)),
        # more frames than the camera takes: cut about the centre
        (ZRange(-5.0, 0.5, 21), StageLimits(-10.0, 10.0, 7), ZRange(-1.5, 0.5, 7)),
        # longer than the travel: the frames that fit, from the bottom
        (ZRange(-3.0, 0.5, 13), StageLimits(-1.0, 1.0, 64), ZRange(-1.0, 0.5, 5)),
        # one frame beyond the travel: at its edge
        (ZRange(50.0, 0.5, 1), StageLimits(-10.0, 10.0, 8), ZRange(10.0, 0.5, 1)),
        # nothing stated: unchanged
        (ZRange(500.0, 0.5, 90), StageLimits(), ZRange(500.0, 0.5, 90)),
    ],
)
def test_a_stack_is_fitted_to_the_stage_travel_and_frame_limit(
    asked: ZRange, limits: StageLimits, taken: ZRange
) -> None:
    fitted = limits.fit(asked)
    assert fitted.n_frames == taken.n_frames and fitted.step_um == asked.step_um
    assert fitted.low_um == pytest.approx(taken.low_um)


@pytest.mark.parametrize("step_um", [0.1, 0.3, 0.7, 1 / 3])
def test_a_fitted_stack_never_reaches_a_hair_beyond_the_travel(step_um: float) -> None:
    """The instrument refuses a frame a rounding error above its travel like any other."""
    limits = StageLimits(-0.7, 0.9, 64)
    for center_um in np.linspace(-3.0, 3.0, 61):
        for n_frames in (1, 2, 5, 17, 40):
            fitted = limits.fit(ZRange.centred(float(center_um), n_frames, step_um))
            assert fitted.n_frames >= 1
            assert limits.z_min_um is not None and limits.z_max_um is not None
            assert fitted.low_um >= limits.z_min_um and fitted.high_um <= limits.z_max_um


def test_stacks_are_kept_within_what_the_instrument_takes() -> None:
    """The slide's policy asks for no more frames than the instrument takes, and every stack,
    phase stacks too, lies within the stage's travel, even where the estimator asks beyond
    it (a focus near its top)."""
    grid = ScanGrid(2, 3)
    truth_um = np.array([[0.0, 0.8, 1.6], [0.9, 1.5, 1.95]])
    limits = StageLimits(-2.0, 2.0, 4)
    geometry = SlideGeometry(grid, dof_um=0.9, stage=limits)
    request = replace(REQUEST, phase=PhaseStacks(planes=11))
    fake = FakeEstimator(grid, truth_um, frozenset())

    steps, _ = drive(request, fake.answer(geometry))
    (create,) = [s for s in steps if isinstance(s, CreateOrResumeSlide)]
    assert create.config.z_range.max_frames == 4
    assert create.config.z_range.min_frames <= 4
    acquired = [s for s in steps if isinstance(s, Acquire)]
    for step in acquired:
        z = step.acquisition.z
        assert z.n_frames <= 4 and z.low_um >= -2.0 and z.high_um <= 2.0
    # the fake asks for 5 frames: every stack was cut, and some moved down from above 2 um
    assert all(s.asked is not None and s.asked.n_frames == 5 for s in acquired)
    assert any(s.asked is not None and s.asked.high_um > 2.0 for s in acquired)
    for step in (s for s in steps if isinstance(s, AcquirePhase)):
        assert step.z.n_frames == 4 and step.z.low_um >= -2.0 and step.z.high_um <= 2.0
    # every tile still imaged at its focus
    last_kept = {(s.row, s.col): s.z_um for s in steps if isinstance(s, KeepTile)}
    for (row, col), z_um in last_kept.items():
        assert abs(z_um - truth_um[row, col]) <= STEP_UM / 2


def test_a_policy_asks_for_no_more_frames_than_the_instrument_takes() -> None:
    policy = REQUEST.policy
    assert StageLimits(max_frames=policy.max_frames + 5).limit_policy(policy) == policy
    assert StageLimits().limit_policy(policy) == policy
    limited = StageLimits(max_frames=2).limit_policy(policy)
    assert (limited.min_frames, limited.max_frames) == (2, 2)
    assert limited.k_sigma == policy.k_sigma and limited.z_step_um == policy.z_step_um


def test_a_tile_too_unsure_for_one_frame_keeps_the_frames_its_outcome_names() -> None:
    """Where the outcome names several frames to keep (after an image-only stack for more of
    them), the plan keeps each of them, from the tile's own stacks."""
    grid = ScanGrid(3, 3)
    truth_um = np.random.default_rng(2).normal(0.0, 0.4, grid.shape)
    geometry = SlideGeometry(grid, dof_um=0.9)
    fake = FakeEstimator(grid, truth_um, frozenset({(0, 1), (2, 2)}))

    steps, _ = drive(REQUEST, fake.answer(geometry))
    planes_acquired = [
        s for s in steps if isinstance(s, Acquire) and s.acquisition.purpose == Purpose.PLANES
    ]
    assert len(planes_acquired) == 2
    assert not any(a.acquisition.measure for a in planes_acquired)  # image only
    awaited = {s.acquisition.index for s in steps if isinstance(s, AwaitFocus)}
    assert not awaited & {a.acquisition.index for a in planes_acquired}
    kept = [s for s in steps if isinstance(s, KeepPlanes)]
    named = {(o.row, o.col): o.planes_um for o in fake.outcomes if o.planes_um}
    assert set(named) == {(0, 1), (2, 2)}
    assert {(s.row, s.col): tuple(f.z_um for f in s.planes) for s in kept} == named
    for step in kept:  # each a frame of this tile's own stacks, both stacks among them
        sequences = {
            s.acquisition.index
            for s in steps
            if isinstance(s, Acquire)
            and (s.acquisition.row, s.acquisition.col) == (step.row, step.col)
        }
        assert {frame.sequence for frame in step.planes} == sequences


def test_an_edge_peak_is_posted_and_the_image_may_come_from_an_earlier_stack() -> None:
    first = acquisition(0, 0, 0, low_um=-1.0)  # frames -1.0 .. 1.0
    retry = acquisition(1, 0, 0, low_um=1.5)  # frames 1.5 .. 3.5
    nexts = iter([first, retry, None])
    posted: list[Measurement] = []

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "s"
            case AskNext():
                return next(nexts)
            case Acquire():
                return tuple(step.acquisition.z.z_um())
            case AwaitFocus() if step.acquisition is first:
                return focus(first, 1.0, FocusFlag.EDGE_HIGH.proto)
            case AwaitFocus():
                return focus(retry, 1.55)
            case PostMeasurement():
                posted.append(step.measurement)
                if step.acquisition is first:  # not an observation: no estimate yet
                    return Outcome(0, 0, accepted=False)
                return Outcome(0, 0, accepted=True, posterior_um=1.2)

    steps, _ = drive(REQUEST, answer)
    assert posted[0].flags == {FocusFlag.EDGE_HIGH} and not posted[0].is_observation
    assert posted[1] == Measurement(1.55, 0.05)
    kept = [(s.sequence, s.frame, s.z_um) for s in steps if isinstance(s, KeepTile)]
    # Before each post, the frame nearest the measured z; after the last, the frame nearest
    # the posterior 1.2 um: the first stack's top frame (1.0), not the retry's 1.5.
    assert kept == [(0, 4, 1.0), (1, 0, 1.5), (0, 4, 1.0)]
    posts = [i for i, s in enumerate(steps) if isinstance(s, PostMeasurement)]
    assert all(isinstance(steps[i - 1], KeepTile) for i in posts)


def test_a_lost_focus_result_is_acquired_again_then_the_scan_stops_naming_the_key() -> None:
    only = acquisition(7, 1, 0, low_um=0.0)
    request = ScanOptions.defaults(focus_attempts=2).request("sim", "slide-0", "kf-wiener0")

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "s"
            case AskNext():
                return only
            case Acquire():
                return tuple(only.z.z_um())
            case AwaitFocus():
                return None  # timed out

    seen: list[Step] = []

    def record(step: Step) -> Any:
        seen.append(step)
        return answer(step)

    with pytest.raises(FocusUnavailableError, match=r"focustrack/v1/focus/slide-0/1/0.*2 attempt"):
        drive(request, record)
    assert [s.attempt for s in seen if isinstance(s, Acquire)] == [1, 2]
    assert not any(isinstance(s, PostMeasurement) for s in seen)


def test_an_image_only_acquisition_waits_for_no_focus_and_keeps_its_single_frame() -> None:
    single = acquisition(3, 1, 1, low_um=0.25, n=1, measure=False)
    nexts = iter([single, None])

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "resumed-id"
            case AskNext():
                return next(nexts)
            case Acquire():
                return (0.25,)
            case PostMeasurement():
                assert step.measurement == Measurement(z_um=None)
                return Outcome(1, 1, accepted=False, posterior_um=0.25)
            case AwaitFocus():
                pytest.fail("an image-only acquisition has no focus result")

    resumed = replace(
        DEFAULTS.request("sim", "slide-0", "af-every-tile"), resume_slide_id="resumed-id"
    )
    steps, slide_id = drive(resumed, answer)
    assert slide_id == "resumed-id"
    create = next(s for s in steps if isinstance(s, CreateOrResumeSlide))
    assert create.slide_id == "resumed-id" and create.config.strategy == "af-every-tile"
    assert [s for s in steps if isinstance(s, KeepTile)] == [KeepTile(1, 1, 3, 0, 0.25)]


def test_on_a_phase_scan_a_frame_only_imaged_is_a_look_and_glass_takes_no_phase_stack() -> None:
    """A tile imaged with one frame at a sure prediction was never measured, so nothing said
    it was glass and it took a phase stack of glass. On a phase scan its frame is awaited as
    the look the focus service reads it as: empty takes no phase stack; something in view,
    or a look that does not come, takes one; the look's flags are posted and logged (a
    resumed scan knows the glass), and a frame only imaged again is never awaited twice."""
    grid = ScanGrid(1, 3)
    glass, cells, lost = (
        acquisition(i, 0, i - 1, low_um=0.25, n=1, measure=False) for i in (1, 2, 3)
    )
    nexts = iter([glass, cells, lost, None])
    looks = {glass.index: (FocusFlag.EMPTY.proto, FocusFlag.FLAT.proto), cells.index: ()}
    posted: dict[int, Measurement] = {}

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return SlideGeometry(grid, dof_um=0.9)
            case CreateOrResumeSlide():
                return "slide-id"
            case AskNext():
                return next(nexts)
            case Acquire():
                return (0.25,)
            case AwaitFocus():
                assert step.look_only
                flags = looks.get(step.acquisition.index)
                return None if flags is None else focus(step.acquisition, None, *flags)
            case PostMeasurement():
                posted[step.acquisition.index] = step.measurement
                acq = step.acquisition
                return Outcome(acq.row, acq.col, accepted=False, posterior_um=0.25)
            case TilesWithoutPhase():
                return []
            case _:
                return True

    steps, _ = drive(replace(REQUEST, phase=PhaseStacks(planes=5)), answer)
    assert [(s.row, s.col) for s in steps if isinstance(s, AcquirePhase)] == [(0, 1), (0, 2)]
    assert sum(isinstance(s, AwaitFocus) for s in steps) == 3
    assert posted[glass.index] == Measurement(
        z_um=None, flags=frozenset({FocusFlag.EMPTY, FocusFlag.FLAT})
    )
    assert posted[cells.index] == posted[lost.index] == Measurement(z_um=None)
    # without phase, no look is awaited: the scan does not wait on the focus service there
    nexts = iter([glass, cells, lost, None])
    steps, _ = drive(REQUEST, answer)
    assert not any(isinstance(s, AwaitFocus | AcquirePhase) for s in steps)


def test_frames_of_a_previous_tile_are_never_kept_for_the_next() -> None:
    a = acquisition(0, 0, 0, low_um=5.0)
    b = acquisition(1, 0, 1, low_um=-1.0)
    nexts = iter([a, b, None])

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "s"
            case AskNext():
                return next(nexts)
            case Acquire():
                return tuple(step.acquisition.z.z_um())
            case AwaitFocus():
                return focus(step.acquisition, step.acquisition.z.center_um)
            case PostMeasurement():
                acq = step.acquisition
                return Outcome(acq.row, acq.col, accepted=True, posterior_um=6.0)

    steps, _ = drive(REQUEST, answer)
    kept = [(s.col, s.sequence, s.z_um) for s in steps if isinstance(s, KeepTile)]
    # tile 0: the centre frame (measured), then the top one (posterior 6.0); tile 1 cannot
    # take tile 0's frame at 6.0: its own top frame is the nearest
    assert kept == [(0, 0, 6.0), (1, 1, 0.0), (1, 1, 1.0)]


def test_measurement_of_focus_results() -> None:
    acq = acquisition(0, 0, 0, low_um=0.0)
    assert measurement_of(focus(acq, 0.8, FocusFlag.MULTI_PEAK.proto)) == Measurement(
        0.8, 0.05, frozenset({FocusFlag.MULTI_PEAK})
    )
    assert measurement_of(focus(acq, None, FocusFlag.FLAT.proto)) == Measurement(
        None, flags=frozenset({FocusFlag.FLAT})
    )
    # a sigma the estimator would refuse is left out; a flag from a newer service is ignored
    assert measurement_of(focus(acq, 0.8, 99, sigma_um=0.0)) == Measurement(0.8)
    # the choice between peaks travels on; one the estimator would refuse is left out
    chosen = focus(acq, 0.8, FocusFlag.MULTI_PEAK.proto)
    chosen.runner_up_z_um, chosen.chosen_probability = 3.5, 0.7
    assert measurement_of(chosen) == Measurement(
        0.8, 0.05, frozenset({FocusFlag.MULTI_PEAK}), runner_up_z_um=3.5, chosen_probability=0.7
    )
    chosen.runner_up_z_um, chosen.chosen_probability = float("nan"), 1.5
    assert measurement_of(chosen) == Measurement(0.8, 0.05, frozenset({FocusFlag.MULTI_PEAK}))
    broken = focus(acq, 0.8)
    broken.error.CopyFrom(common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK, message="x"))
    assert measurement_of(broken) == Measurement(None)


def test_a_focus_result_out_of_the_apis_bounds_is_posted_within_them() -> None:
    """A focus service in valley mode stated a sigma of 0.00084 um; posting it failed the
    API's model (sigma >= 0.001 um) and ended the scan with a traceback."""
    acq = acquisition(0, 0, 0, low_um=0.0)
    cases = [
        (focus(acq, 0.8, sigma_um=0.00084), Measurement(0.8, api.MIN_SIGMA_UM)),
        (focus(acq, 0.8, sigma_um=1e9), Measurement(0.8, api.MAX_ABS_UM)),
        (focus(acq, float("inf")), Measurement(None)),
        (focus(acq, -2e6), Measurement(None)),
    ]
    for result, expected in cases:
        measurement = measurement_of(result)
        assert measurement == expected
        to_api.measurement_in(acq, measurement)  # what the engine posts: valid
    beyond = focus(acq, 0.8, FocusFlag.MULTI_PEAK.proto)
    beyond.runner_up_z_um = 2e6
    assert measurement_of(beyond).runner_up_z_um is None


def test_bad_requests_are_refused_before_any_step() -> None:
    with pytest.raises(ValueError, match="instrument"):
        DEFAULTS.request("no/slash", "slide-0", "kf-wiener0")
    with pytest.raises(ValueError, match="focus_attempts"):
        replace(REQUEST, focus_attempts=0)


def test_a_revisit_is_measured_and_posted_and_leaves_the_tiles_image() -> None:
    a = acquisition(0, 0, 0, low_um=-1.0)
    b = acquisition(1, 0, 1, low_um=-1.0)
    revisit = replace(acquisition(2, 0, 0, low_um=2.0, n=3), purpose=Purpose.REVISIT)
    c = acquisition(3, 1, 1, low_um=-1.0)
    nexts = iter([a, b, revisit, c, None])
    posted: list[Acquisition] = []

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "s"
            case AskNext():
                return next(nexts)
            case Acquire():
                return tuple(step.acquisition.z.z_um())
            case AwaitFocus():
                return focus(step.acquisition, step.acquisition.z.center_um)
            case PostMeasurement():
                acq = step.acquisition
                posted.append(acq)
                if acq.purpose is Purpose.REVISIT:
                    assert step.measurement.z_um == pytest.approx(2.5)
                    return Outcome(acq.row, acq.col, accepted=True, innovation_um=0.1)
                return Outcome(acq.row, acq.col, accepted=True, posterior_um=0.0)

    steps, _ = drive(REQUEST, answer)
    assert [acq.index for acq in posted] == [0, 1, 2, 3]
    kept = [(s.row, s.col, s.sequence) for s in steps if isinstance(s, KeepTile)]
    assert kept == [(0, 0, 0), (0, 1, 1), (1, 1, 3)]  # tile (0, 0) keeps its first image


def test_a_second_pass_matches_each_final_image_and_retakes_the_tiles_before_the_offset() -> None:
    """With `realign`, every tile's final image is matched against the first pass's; the
    tiles the answer names (those imaged before the offset was known) are taken again, one
    frame at their image's z, each under its own wire sequence."""
    grid = ScanGrid(2, 3)
    truth_um = np.random.default_rng(5).normal(0.0, 0.4, grid.shape)
    geometry = SlideGeometry(grid, dof_um=0.9)
    fake = FakeEstimator(grid, truth_um, frozenset())
    answer = fake.answer(geometry)
    matched: list[MatchTile] = []

    def with_matches(step: Step) -> Any:
        if isinstance(step, MatchTile):  # the offset is known at the second tile
            matched.append(step)
            if len(matched) == 2:
                return [(m.image.row, m.image.col, m.image.z_um) for m in matched]
            return []
        return None if isinstance(step, Retake) else answer(step)

    request = replace(REQUEST, realign=Realign(Path("first-pass")))
    steps, _ = drive(request, with_matches)
    kept = {(s.row, s.col): s for s in steps if isinstance(s, KeepTile)}
    assert [kept[(m.image.row, m.image.col)] for m in matched] == [m.image for m in matched]
    assert [(m.image.row, m.image.col) for m in matched] == [
        (t.row, t.col) for t in grid.serpentine
    ]
    retaken = [s for s in steps if isinstance(s, Retake)]
    assert [(r.row, r.col, r.z_um) for r in retaken] == [
        (m.image.row, m.image.col, m.image.z_um) for m in matched[:2]
    ]
    assert all(r.sequence == RETAKE_SEQUENCE_BASE + r.row * grid.cols + r.col for r in retaken)
    plain, _ = drive(REQUEST, FakeEstimator(grid, truth_um, frozenset()).answer(geometry))
    assert plain == [s for s in steps if not isinstance(s, MatchTile | Retake)]


@pytest.mark.parametrize(
    ("ratio", "min_ratio", "flagged"),
    [(0.7, 0.9, True), (0.95, 0.9, False), (None, 0.9, False), (0.7, 0.0, False)],
)
def test_a_second_pass_compares_a_tiles_one_frame_and_posts_it_out_of_focus(
    ratio: float | None, min_ratio: float, flagged: bool
) -> None:
    """With `realign`, a tile imaged once at its prediction (no measurement) is compared with
    the first pass's image after its frame is kept and before it is posted: a sharpness
    ratio below `min_sharpness_ratio` posts it `frame_out_of_focus` (none compared: as it
    was; a ratio of 0 compares nothing). A measured stack is never compared."""
    single = acquisition(3, 1, 1, low_um=0.25, n=1, measure=False)
    stack = acquisition(4, 1, 1, low_um=-0.75)
    nexts = iter([single, stack, None])
    posted: list[Measurement] = []
    compared: list[CompareFrame] = []

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return GEOMETRY
            case CreateOrResumeSlide():
                return "slide-id"
            case AskNext():
                return next(nexts)
            case Acquire():
                return tuple(step.acquisition.z.z_um())
            case AwaitFocus():
                return focus(step.acquisition, 0.3)
            case CompareFrame():
                compared.append(step)
                return ratio
            case PostMeasurement():
                posted.append(step.measurement)
                if not step.acquisition.measure:
                    return Outcome(1, 1, accepted=False, posterior_um=None)
                return Outcome(1, 1, accepted=True, posterior_um=0.3)
            case MatchTile():
                return []

    realign = Realign(Path("first-pass"), min_sharpness_ratio=min_ratio)
    steps, _ = drive(replace(REQUEST, realign=realign), answer)
    assert compared == ([] if min_ratio == 0 else [CompareFrame(KeepTile(1, 1, 3, 0, 0.25))])
    if compared:  # after its frame is kept, before it is posted
        at = steps.index(compared[0])
        assert steps[at - 1] == compared[0].image and isinstance(steps[at + 1], PostMeasurement)
    assert posted == [Measurement(z_um=None, frame_out_of_focus=flagged), measurement_of(
        focus(stack, 0.3)
    )]  # fmt: skip


def test_a_sharpness_ratio_is_a_share_below_one() -> None:
    with pytest.raises(ValueError, match="sharpness ratio"):
        Realign(Path("first-pass"), min_sharpness_ratio=1.0)
