"""The lean rule's pairs (`short_frames` 2): two frames one z step apart where it would take
three, a reach beyond them, and one more frame where the peak lies beyond their depth of
field."""

from __future__ import annotations

import math

import pytest
from scipy.stats import norm

from focustrack_core.domain import PAIR_FRAMES, PAIR_REACH_UM, Measurement, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_policy, default_settings
from focustrack_estimator import registry
from focustrack_estimator.lean import (
    SHORT_FRAMES,
    choose_stack,
    frame_at_peak,
    search_cost,
    skip_risk,
)

POLICY = default_policy()  # z step 0.5 um, retries of at least 5 frames
DOF_UM = 1.0


def test_a_pair_replaces_the_short_stack_where_the_rule_would_take_three_frames() -> None:
    three = choose_stack(2.0, 0.3**2, 0.1**2, DOF_UM, POLICY, 0.01, skip_risk(0.3, DOF_UM, 1.0), 3)
    two = choose_stack(
        2.0, 0.3**2, 0.1**2, DOF_UM, POLICY, 0.01, skip_risk(0.3, DOF_UM, 1.0), 3, PAIR_FRAMES
    )
    assert three.measure and three.z.n_frames == SHORT_FRAMES
    assert two.measure and two.z.n_frames == PAIR_FRAMES
    assert two.z.step_um == POLICY.z_step_um and two.z.center_um == pytest.approx(2.0)
    assert two.expected_frames < three.expected_frames


def test_a_pair_reaches_beyond_its_frames_and_counts_the_frame_at_a_peak_out_there() -> None:
    pair = choose_stack(
        0.0, 0.5**2, 0.0, DOF_UM, POLICY, 0.01, skip_risk(0.5, DOF_UM, 1.0), 3, PAIR_FRAMES
    ).z
    sigma_um = 0.5
    reach_um = 0.25 + PAIR_REACH_UM  # then retries of 5 frames reaching 1.5 um further each
    expected = 2.0 + 2 * norm.sf((0.25 + DOF_UM / 2) / sigma_um)
    for k in range(3):
        expected += 5 * 2 * norm.sf((reach_um + 1.5 * k) / sigma_um)
    cost = search_cost(pair, sigma_um, POLICY, 3, 0.01, DOF_UM)
    assert cost == pytest.approx(expected)
    # the same two frames without the reach would miss the peak most of the time
    assert cost < 2.0 + 5 * 2 * norm.sf(0.25 / sigma_um)


def test_one_frame_at_the_peak_where_it_alone_is_sure_enough() -> None:
    frame = frame_at_peak(3.2, 0.1, DOF_UM, 0.5, 0.01)
    assert frame is not None and frame.n_frames == 1 and frame.center_um == 3.2
    assert frame_at_peak(3.2, 0.4, DOF_UM, 0.5, 0.01) is None  # 0.5 / 0.4: a risk of 21%


def test_kf_2d_lean_with_pairs_images_a_peak_beyond_its_pair_with_one_more_frame() -> None:
    settings = default_settings(ScanGrid(1, 3), start_sigma_um=0.3, noise_sigma_um=0.1)
    strategy = registry.create("kf-2d-lean", settings, {"short_frames": 2})
    pair = strategy.next_acquisition()
    assert pair is not None and pair.measure and pair.z.n_frames == PAIR_FRAMES
    peak_um = pair.z.high_um + 0.6  # beyond the frames, within the pair's reach
    outcome = strategy.record(pair, Measurement(peak_um, 0.05))
    assert outcome.accepted
    at_peak = strategy.next_acquisition()
    assert at_peak is not None and at_peak.purpose == Purpose.PLANES
    assert at_peak.z.n_frames == 1 and not at_peak.measure
    assert at_peak.z.center_um == pytest.approx(outcome.posterior_um)
    strategy.record(at_peak, Measurement(None))
    kept_um = strategy.focus_map().z_used_um[0, 0]
    assert kept_um == pytest.approx(at_peak.z.center_um)
    assert abs(kept_um - peak_um) < DOF_UM / 2
    following = strategy.next_acquisition()
    assert following is not None and (following.row, following.col) != (0, 0)
    assert math.isfinite(strategy.focus_map().out_of_focus_risk[0, 0])


def test_short_frames_is_two_or_three() -> None:
    settings = default_settings(ScanGrid(2, 2))
    with pytest.raises(ValueError, match="short_frames"):
        registry.create("kf-2d-lean", settings, {"short_frames": 1})
    with pytest.raises(ValueError, match="short_frames"):
        registry.create("kf-2d-lean", settings, {"short_frames": 4})
