"""`look_first`: a tile's first stack is its lowest frame alone (a look), then the rest where
something is in view, so that an empty tile costs one frame and a tile with tissue no frame
more than its stack."""

from __future__ import annotations

import pytest

from focustrack_core.domain import FocusFlag, Measurement, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_estimator import registry
from focustrack_estimator.look_first import LOOK_REACH_UM, first_part, with_look
from focustrack_estimator.serpentine import SerpentineFilter

EMPTY = Measurement(None, flags=frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))
IN_VIEW = Measurement(None)  # a look that saw something: no focus, no flag
SIGMA_UM = 0.1


def test_a_short_stack_is_its_lowest_frame_then_the_rest() -> None:
    short = ZRange(-0.5, 0.5, 3)
    look = first_part(short, None)
    assert look == ZRange(-0.5, 0.5, 1)
    rest = first_part(short, look)
    assert rest == ZRange(0.0, 0.5, 2)
    assert with_look(look, rest) == short  # the curve the focus service reads
    assert with_look(None, rest) == rest and with_look(look, short) == short


def test_a_wide_stack_is_looked_at_its_centre_then_taken_whole() -> None:
    """Where the height is unsure (a wide or coarse stack: a slide's first tile) the look is
    one frame at the prediction, and the whole stack follows where something is in view."""
    wide = ZRange.centred(0.0, 7, 0.5)  # its lowest frame 1.5 um from its centre
    assert wide.center_um - wide.low_um > LOOK_REACH_UM
    look = first_part(wide, None)
    assert look == ZRange(0.0, 0.5, 1) and first_part(wide, look) == wide
    coarse = ZRange.centred(3.0, 15, 4.0)
    assert first_part(coarse, None) == ZRange(3.0, 4.0, 1)
    assert first_part(ZRange(0.0, 0.5, 1), None) == ZRange(0.0, 0.5, 1)  # one frame: as is
    glass_look = ZRange(0.0, 0.5, 1)  # at the prediction, not the stack's lowest frame
    assert first_part(ZRange(-0.5, 0.5, 3), glass_look) == ZRange(-0.5, 0.5, 3)


def test_a_pair_is_its_lower_frame_then_the_upper() -> None:
    pair = ZRange(-0.25, 0.5, 2)
    look = first_part(pair, None)
    assert look == ZRange(-0.25, 0.5, 1)
    rest = first_part(pair, look)
    assert rest == ZRange(0.25, 0.5, 1) and with_look(look, rest) == pair


def lean_with_look_first(cols: int) -> SerpentineFilter:
    """A lean filter sure enough of its first tile for a short stack (kf-2d-lean's first
    tiles take a wide stack: its bank starts unsure), with look_first."""
    settings = default_settings(
        ScanGrid(1, cols), start_z_um=0.0, start_sigma_um=0.3, noise_sigma_um=0.1
    )
    params = {"risk_out_of_focus": 0.01, "look_first": True}
    strategy = registry.create("kf-wiener0", settings, params)
    assert isinstance(strategy, SerpentineFilter)
    return strategy


def test_an_empty_tile_costs_one_frame_and_a_tile_in_view_its_stack() -> None:
    strategy = lean_with_look_first(3)
    look = strategy.next_acquisition()
    assert look is not None and look.col == 0 and look.z.n_frames == 1
    assert look.purpose is Purpose.SCAN and look.measure
    outcome = strategy.record(look, EMPTY)  # nothing in view: the tile is done
    assert strategy.empty[0, 0] and strategy.map.z_used_um[0, 0] == look.z.low_um
    assert outcome.posterior_um == outcome.prior_um
    look = strategy.next_acquisition()
    assert look is not None and look.col == 1 and look.z.n_frames == 1
    assert not strategy.record(look, IN_VIEW).accepted  # something in view
    rest = strategy.next_acquisition()
    assert rest is not None and rest.col == 1 and rest.purpose is Purpose.SCAN
    assert rest.z.low_um == pytest.approx(look.z.low_um + rest.z.step_um)
    total = look.z.n_frames + rest.z.n_frames
    # the rest's peak at the look's frame (the curve's lower edge): the search continues
    # below the look, not over it
    edge = Measurement(look.z.low_um, SIGMA_UM, frozenset({FocusFlag.EDGE_LOW}))
    assert strategy.record(rest, edge).posterior_um is None  # not done yet
    retry = strategy.next_acquisition()
    assert retry is not None and retry.purpose is Purpose.RETRY
    assert retry.z.high_um == pytest.approx(look.z.low_um + retry.z.step_um)
    assert strategy.record(retry, Measurement(look.z.low_um - 0.05, SIGMA_UM)).accepted
    assert total == 3 and not strategy.empty[0, 1]
    # the look's frame is one of the tile's: the one nearest its focus here
    assert strategy.map.z_used_um[0, 1] == pytest.approx(look.z.low_um)


def test_where_the_height_is_unknown_glass_costs_one_frame_and_tissue_one_more() -> None:
    """A slide's first tiles (10 um unsure: a coarse stack) are looked at the prediction
    first: glass is done with that frame, a tile in view takes its coarse stack whole."""
    settings = default_settings(
        ScanGrid(1, 3), start_z_um=0.0, start_sigma_um=10.0, noise_sigma_um=0.1
    )
    strategy = registry.create("kf-2d-lean", settings, {"look_first": True})
    assert isinstance(strategy, SerpentineFilter)
    look = strategy.next_acquisition()
    assert look is not None and look.z.n_frames == 1 and look.z.low_um == pytest.approx(0.0)
    strategy.record(look, EMPTY)
    assert strategy.empty[0, 0] and strategy.scanned[0, 0]  # one frame in all
    look = strategy.next_acquisition()
    assert look is not None and look.col == 1 and look.z.n_frames == 1
    strategy.record(look, IN_VIEW)
    coarse = strategy.next_acquisition()
    assert coarse is not None and coarse.col == 1 and coarse.z.n_frames > 5
    assert coarse.z.step_um > 1.0 and coarse.purpose is Purpose.SCAN  # the coarse search
