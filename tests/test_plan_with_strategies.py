"""The scheduler's scan plan against real strategies of the estimator, run in process.

A strategy made by the estimator's registry from the slide the plan asks for stands in for
the estimator, and `replay.simulated_measurement` of a known map for the focus service: the
plan and the strategies agree on every step (which frames a tile keeps, which stacks are
image only) without a service between them. The plan against a fake estimator is beside
the scheduler (services/scheduler/tests/test_scheduler_plan.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from focustrack_core.domain import Outcome, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import slide_settings
from focustrack_core.v1 import focus_pb2
from focustrack_estimator import registry
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.strategy import Strategy
from focustrack_scheduler.plan import (
    Acquire,
    AskNext,
    AwaitFocus,
    CreateOrResumeSlide,
    DescribeSlide,
    KeepPlanes,
    KeepTile,
    PostMeasurement,
    ScanRequest,
    SlideGeometry,
    Step,
    execute,
    scan_plan,
    slide_config,
)
from focustrack_scheduler.settings import ScanOptions


def drive(request: ScanRequest, answer: Callable[[Step], Any]) -> tuple[list[Step], str]:
    """Run the plan, answering each step with `answer`; the steps and the plan's result."""
    steps: list[Step] = []

    def answer_and_keep(step: Step) -> Any:
        steps.append(step)
        return answer(step)

    return steps, execute(scan_plan(request), answer_and_keep)


def local_services(
    request: ScanRequest, geometry: SlideGeometry, measured_um: np.ndarray
) -> tuple[Strategy, Callable[[Step], Any], list[Outcome]]:
    """The registry's strategy for `request` on `geometry`, standing in for the estimator,
    and `measured_um` (rows, cols) for the focus service: the strategy, the answers to the
    plan's steps and the outcomes, as they come."""
    strategy = registry.create(
        request.strategy, slide_settings(slide_config(request, geometry)), request.params
    )
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
                result = focus_pb2.FocusResult(
                    slide=request.slide,
                    row=acq.row,
                    col=acq.col,
                    sequence=acq.index,
                    flags=[flag.proto for flag in sorted(measured.flags)],
                )
                result.z_um.extend(acq.z.z_um().tolist())
                if measured.z_um is not None:
                    result.best_z_um, result.sigma_um = measured.z_um, 0.05
                return result
            case PostMeasurement():
                outcomes.append(strategy.record(step.acquisition, step.measurement))
                return outcomes[-1]
            case KeepTile() | KeepPlanes():
                return None

    return strategy, answer, outcomes


def test_a_real_strategy_scans_every_tile_and_keeps_the_frame_nearest_each_posterior() -> None:
    """kf-wiener0 for the estimator, the truth for the focus service: every tile keeps the
    frame the strategy uses (its z used), and nine tiles in ten of those lie within 0.45 um
    of the truth."""
    grid = ScanGrid(3, 4)
    truth_um = np.linspace(-3.0, 4.0, grid.n_tiles).reshape(grid.shape)
    request = ScanOptions.defaults(noise_sigma_um=0.1).request("sim", "slide-0", "kf-wiener0")
    geometry = SlideGeometry(grid, dof_um=0.9)
    strategy, answer, _ = local_services(request, geometry, truth_um)

    steps, slide_id = drive(request, answer)
    assert slide_id == "slide-id"
    (create,) = [s for s in steps if isinstance(s, CreateOrResumeSlide)]
    assert create.slide_id is None and create.config.grid.rows == 3
    assert create.config.dof_um == 0.9 and create.config.noise_sigma_um == 0.1
    last_kept = {(s.row, s.col): s for s in steps if isinstance(s, KeepTile)}
    assert set(last_kept) == {(t.row, t.col) for t in grid.serpentine}
    focus_map = strategy.focus_map()
    for (row, col), kept in last_kept.items():  # the strategy's own choice of frame: z used
        assert kept.z_um == pytest.approx(focus_map.z_used_um[row, col])
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
    measured_um = np.random.default_rng(2).normal(0.0, 1.5, grid.shape)
    request = ScanOptions.defaults(noise_sigma_um=1.5).request("sim", "slide-0", "kf-2d-lean")
    _, answer, outcomes = local_services(request, SlideGeometry(grid, dof_um=0.9), measured_um)

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
