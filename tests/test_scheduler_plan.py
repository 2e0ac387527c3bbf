"""The scan plan against fake step results: pure, no services."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from focustrack_core.domain import Acquisition, FocusFlag, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_domain
from focustrack_core.v1 import common_pb2, focus_pb2
from focustrack_estimator import registry
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.strategy import Strategy
from focustrack_scheduler.plan import (
    Acquire,
    AskNext,
    AwaitFocus,
    CreateOrResumeSlide,
    DescribeSlide,
    FocusUnavailableError,
    KeepPlanes,
    KeepTile,
    PostMeasurement,
    ScanRequest,
    SlideGeometry,
    Step,
    measurement_of,
    scan_plan,
    slide_config,
)

GEOMETRY = SlideGeometry(ScanGrid(2, 2), dof_um=0.9)
GEOMETRY_3 = SlideGeometry(ScanGrid(3, 3), dof_um=0.9)
REQUEST = ScanRequest(instrument="sim", slide="slide-0", strategy="kf-wiener0")


def drive(request: ScanRequest, answer: Callable[[Step], Any]) -> tuple[list[Step], str]:
    """Run the plan, answering each step with `answer`; the steps and the plan's result."""
    plan = scan_plan(request)
    steps: list[Step] = []
    result: Any = None
    try:
        while True:
            step = plan.send(result)
            steps.append(step)
            result = answer(step)
    except StopIteration as finished:
        return steps, finished.value


def acquisition(
    index: int, row: int, col: int, low_um: float, n: int = 5, measure: bool = True
) -> Acquisition:
    return Acquisition(index, row, col, ZRange(low_um, 0.5, n), Purpose.SCAN, measure)


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


def local_services(
    strategy: Strategy, geometry: SlideGeometry, measured_um: np.ndarray
) -> tuple[Callable[[Step], Any], list[Outcome]]:
    """Answers to the plan's steps: `strategy` stands in for the estimator and
    `measured_um` (rows, cols) for the focus service; the outcomes, as they come."""
    outcomes: list[Outcome] = []

    def answer(step: Step) -> Any:
        match step:
            case DescribeSlide():
                return geometry
            case CreateOrResumeSlide():
                return "slide-id"
            case AskNext():
                return strategy.next_acquisition()
            case Acquire():
                return tuple(step.acquisition.z.z_um())
            case AwaitFocus():
                acq = step.acquisition
                measured = simulated_measurement(acq, measured_um[acq.row, acq.col])
                return focus(acq, measured.z_um, *(flag.proto for flag in sorted(measured.flags)))
            case PostMeasurement():
                outcomes.append(strategy.record(step.acquisition, step.measurement))
                return outcomes[-1]
            case KeepTile() | KeepPlanes():
                return None

    return answer, outcomes


def test_a_real_strategy_scans_every_tile_and_keeps_the_frame_nearest_each_posterior() -> None:
    """The plan against a local strategy standing in for the estimator, truth for the focus."""
    grid = ScanGrid(3, 4)
    truth_um = np.linspace(-3.0, 4.0, grid.n_tiles).reshape(grid.shape)
    request = ScanRequest("sim", "slide-0", "kf-wiener0", noise_sigma_um=0.1)
    geometry = SlideGeometry(grid, dof_um=0.9)
    strategy = registry.create(
        "kf-wiener0", to_domain.slide_settings(slide_config(request, geometry))
    )
    answer, _ = local_services(strategy, geometry, truth_um)

    steps, slide_id = drive(request, answer)
    assert slide_id == "slide-id"
    (create,) = [s for s in steps if isinstance(s, CreateOrResumeSlide)]
    assert create.slide_id is None and create.config.grid.rows == 3
    assert create.config.dof_um == 0.9 and create.config.noise_sigma_um == 0.1
    last_kept = {(s.row, s.col): s for s in steps if isinstance(s, KeepTile)}
    assert set(last_kept) == {(t.row, t.col) for t in grid.serpentine}
    focus_map = strategy.focus_map()
    for (row, col), k in last_kept.items():  # the strategy's own choice of frame: z used
        assert k.z_um == pytest.approx(focus_map.z_used_um[row, col])
    assert np.mean(np.abs(focus_map.z_used_um - truth_um) <= 0.45) > 0.9
    # Every Acquire is answered by exactly one AwaitFocus (all these stacks are measured).
    assert sum(isinstance(s, Acquire) for s in steps) == sum(
        isinstance(s, AwaitFocus) for s in steps
    )


def test_a_tile_too_unsure_for_one_frame_keeps_the_frames_its_outcome_names() -> None:
    """At 1.5 um of measurement noise against 0.9 um of depth of field, kf-2d-lean names
    several frames to keep of a measured tile (asking for more, image only, where its
    stacks hold too few): the plan keeps each of them."""
    grid = ScanGrid(3, 3)
    rng = np.random.default_rng(2)
    measured_um = rng.normal(0.0, 1.5, grid.shape)
    request = ScanRequest("sim", "slide-0", "kf-2d-lean", noise_sigma_um=1.5)
    strategy = registry.create(
        "kf-2d-lean", to_domain.slide_settings(slide_config(request, GEOMETRY_3))
    )
    answer, outcomes = local_services(strategy, GEOMETRY_3, measured_um)

    steps, _ = drive(request, answer)
    planes_acquired = [
        s for s in steps if isinstance(s, Acquire) and s.acquisition.purpose == Purpose.PLANES
    ]
    assert not any(a.acquisition.measure for a in planes_acquired)  # image only
    awaited = {s.acquisition.index for s in steps if isinstance(s, AwaitFocus)}
    assert not awaited & {a.acquisition.index for a in planes_acquired}
    kept = [s for s in steps if isinstance(s, KeepPlanes)]
    named = {(o.row, o.col): o.planes_um for o in outcomes if o.planes_um}
    assert kept and {(s.row, s.col): tuple(f.z_um for f in s.planes) for s in kept} == named
    for step in kept:  # each a frame of this tile's own stacks
        sequences = {
            s.acquisition.index
            for s in steps
            if isinstance(s, Acquire)
            and (s.acquisition.row, s.acquisition.col) == (step.row, step.col)
        }
        assert {frame.sequence for frame in step.planes} <= sequences


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
    request = ScanRequest("sim", "slide-0", "kf-wiener0", focus_attempts=2)

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

    resumed = ScanRequest("sim", "slide-0", "af-every-tile", resume_slide_id="resumed-id")
    steps, slide_id = drive(resumed, answer)
    assert slide_id == "resumed-id"
    create = next(s for s in steps if isinstance(s, CreateOrResumeSlide))
    assert create.slide_id == "resumed-id" and create.config.strategy == "af-every-tile"
    assert [s for s in steps if isinstance(s, KeepTile)] == [KeepTile(1, 1, 3, 0, 0.25)]


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
    broken = focus(acq, 0.8)
    broken.error.CopyFrom(common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK, message="x"))
    assert measurement_of(broken) == Measurement(None)


def test_bad_requests_are_refused_before_any_step() -> None:
    with pytest.raises(ValueError, match="instrument"):
        ScanRequest("no/slash", "slide-0", "kf-wiener0")
    with pytest.raises(ValueError, match="focus_attempts"):
        ScanRequest("sim", "slide-0", "kf-wiener0", focus_attempts=0)
