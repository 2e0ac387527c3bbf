"""A scan whose sure start takes pairs teaches the focus service the slide's curve when its
pairs come back vague two in a row: a stack of fine frames over the curve's width on the
next measured tile, up to the curves the service needs to know the width's spread."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest

from focustrack_core.domain import (
    CURVE_LEARN_FRAMES,
    CURVE_SPREAD_CURVES,
    PAIR_FRAMES,
    Acquisition,
    FocusFlag,
    Measurement,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_policy, default_settings
from focustrack_estimator import registry
from focustrack_estimator.lean import COARSE_STEP_UM, teaching_stack
from focustrack_estimator.serpentine import VAGUE_IN_A_ROW

POLICY = default_policy()  # z step 0.5 um, at most 41 frames
#: A pair read without the slide's curve spread (`focustrack_focus.curve_model`): about a um.
VAGUE_SIGMA_UM = 1.1


def test_a_teaching_stack_spans_the_curves_width_either_side_in_fine_frames() -> None:
    stack = teaching_stack(1.3, POLICY, COARSE_STEP_UM)
    assert stack.step_um == POLICY.z_step_um and stack.center_um == pytest.approx(1.3)
    assert stack.n_frames == 17  # +/- 4 um at 0.5 um
    assert teaching_stack(0.0, POLICY, 0.5).n_frames == CURVE_LEARN_FRAMES  # never fewer
    assert teaching_stack(0.0, POLICY, 100.0).n_frames == POLICY.max_frames  # never more


def _measured_in_a_scan(short: Callable[[Acquisition], Measurement]) -> list[Acquisition]:
    """Every measured acquisition of kf-2d-lean with pairs on 5x5 tiles, started as sure as a
    laser's calibrated offset: stacks of fewer than CURVE_LEARN_FRAMES frames answered by
    `short`, longer ones with a clean peak at their centre."""
    settings = default_settings(ScanGrid(5, 5), start_sigma_um=0.3, noise_sigma_um=0.1)
    strategy = registry.create("kf-2d-lean", settings, {"short_frames": PAIR_FRAMES})
    measured = []
    while (acquisition := strategy.next_acquisition()) is not None:
        if not acquisition.measure:  # a frame only imaged
            strategy.record(acquisition, Measurement(None))
            continue
        measured.append(acquisition)
        long = acquisition.z.n_frames >= CURVE_LEARN_FRAMES
        strategy.record(
            acquisition, Measurement(acquisition.z.center_um, 0.02) if long else short(acquisition)
        )
    return measured


def test_vague_pairs_in_a_row_ask_for_teaching_stacks_up_to_the_curves_the_service_needs() -> None:
    measured = _measured_in_a_scan(lambda pair: Measurement(pair.z.center_um, VAGUE_SIGMA_UM))
    long = [i for i, a in enumerate(measured) if a.z.n_frames >= CURVE_LEARN_FRAMES]
    assert len(long) == CURVE_SPREAD_CURVES
    for i in long:
        teaching, before = measured[i], measured[i - VAGUE_IN_A_ROW : i]
        assert teaching.z == teaching_stack(teaching.predicted_um, POLICY, COARSE_STEP_UM)
        # asked for by vague short stacks in a row, the last of them on the tile before
        assert all(a.z.n_frames < CURVE_LEARN_FRAMES for a in before)
        assert (teaching.row, teaching.col) != (before[-1].row, before[-1].col)
    # the service has the curves it needs: vague pairs after them are each tile's business
    assert sum(a.z.n_frames == PAIR_FRAMES for a in measured[long[-1] :]) >= 3


def test_a_vague_pair_between_sharp_ones_is_one_tiles_business() -> None:
    answers = itertools.cycle([VAGUE_SIGMA_UM, 0.1])
    measured = _measured_in_a_scan(lambda pair: Measurement(pair.z.center_um, next(answers)))
    assert len(measured) >= 10
    assert all(a.z.n_frames < CURVE_LEARN_FRAMES for a in measured)


@pytest.mark.parametrize(
    "short",
    [
        lambda pair: Measurement(pair.z.center_um, 0.1),  # read with the slide's curve
        lambda pair: Measurement(None, None, frozenset({FocusFlag.FLAT, FocusFlag.EMPTY})),
    ],
    ids=["read-with-the-curve", "empty"],
)
def test_pairs_read_with_the_curve_and_empty_fields_ask_for_nothing(
    short: Callable[[Acquisition], Measurement],
) -> None:
    measured = _measured_in_a_scan(short)
    assert len(measured) >= 8
    assert all(a.z.n_frames < CURVE_LEARN_FRAMES for a in measured)
