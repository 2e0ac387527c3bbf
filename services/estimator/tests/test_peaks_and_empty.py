"""What the Kalman strategies learn from `multi_peak` and `empty` measurements: a second
peak that could be the focus widens the measurement's variance (the chosen peak is kept);
one far from the prior (dust) does not; an empty field leaves the surface as it was, and a
tile where glass is half at least of what its scanned neighbours showed is looked at first."""

from __future__ import annotations

import math

import numpy as np
import pytest

from focustrack_client import models as api
from focustrack_core.domain import FocusFlag, Measurement, Purpose
from focustrack_core.geometry import ScanGrid, Tile
from focustrack_core.rest import to_api, to_domain
from focustrack_core.rest.to_domain import default_settings
from focustrack_estimator import registry
from focustrack_estimator.peaks import between_peaks_var_um2
from focustrack_estimator.records import measurement_of, measurement_record
from focustrack_estimator.serpentine import SerpentineFilter, in_glass, is_look

START_SIGMA_UM = 2.0
SIGMA_UM = 0.1


def first_tile(measurement: Measurement, name: str = "kf-2d") -> tuple[float, float, float]:
    """The first tile's prior sigma and posterior (mean, sigma) given `measurement` (um);
    the prior's mean is 0."""
    settings = default_settings(ScanGrid(3, 3), start_z_um=0.0, start_sigma_um=START_SIGMA_UM)
    strategy = registry.create(name, settings)
    assert isinstance(strategy, SerpentineFilter)
    outcome = strategy.record(strategy.next_acquisition(), measurement)
    assert outcome.accepted and outcome.prior_um == 0.0
    assert outcome.prior_sigma_um is not None and outcome.posterior_um is not None
    assert outcome.posterior_sigma_um is not None
    return outcome.prior_sigma_um, outcome.posterior_um, outcome.posterior_sigma_um


def kalman_update(prior_sigma_um: float, z_um: float, r_um2: float) -> tuple[float, float]:
    """The posterior (mean, sigma) from the prior N(0, prior_sigma_um^2) and one measurement."""
    gain = prior_sigma_um**2 / (prior_sigma_um**2 + r_um2)
    return gain * z_um, math.sqrt((1.0 - gain) * prior_sigma_um**2)


def multi_peak(z_um: float, runner_up_um: float, probability: float) -> Measurement:
    return Measurement(z_um, SIGMA_UM, frozenset({FocusFlag.MULTI_PEAK}), runner_up_um, probability)


@pytest.mark.parametrize("name", ["kf-2d", "kf-wiener0"])
def test_a_second_peak_near_the_prior_widens_the_measurement(name: str) -> None:
    prior_sigma_um, mean_um, sigma_um = first_tile(multi_peak(1.0, 4.0, 0.8), name)
    widened_um = math.sqrt(SIGMA_UM**2 + 0.2 * 3.0**2)  # sigma^2 + (1 - p) (z2 - z)^2
    assert (mean_um, sigma_um) == pytest.approx(first_tile(Measurement(1.0, widened_um), name)[1:])
    if name == "kf-wiener0":  # a scalar filter: the textbook update
        assert (mean_um, sigma_um) == pytest.approx(
            kalman_update(prior_sigma_um, 1.0, widened_um**2)
        )
    _, alone_um, alone_sigma_um = first_tile(Measurement(1.0, SIGMA_UM), name)
    assert sigma_um > 2 * alone_sigma_um  # counted, but less sure than a single peak
    assert 0.0 < mean_um < alone_um  # towards the chosen peak, never the runner-up's 4 um


def test_a_second_peak_far_from_the_prior_adds_nothing() -> None:
    # dust 50 um above: no focus this tile could have (the prior is 0 +/- 2 um)
    assert first_tile(multi_peak(1.0, 50.0, 0.6)) == pytest.approx(
        first_tile(Measurement(1.0, SIGMA_UM))
    )
    # a multi_peak flag without the runner-up (an older focus service): the sigma stands
    flagged = Measurement(1.0, SIGMA_UM, frozenset({FocusFlag.MULTI_PEAK}))
    assert between_peaks_var_um2(flagged, 0.0, 4.0, 3.0) == 0.0


def test_an_empty_field_does_not_pull_the_surface() -> None:
    settings = default_settings(ScanGrid(1, 5), start_z_um=0.0, start_sigma_um=START_SIGMA_UM)
    empty = Measurement(None, flags=frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))
    maps = {}
    for middle in ("empty", "measured"):
        strategy = registry.create("kf-2d", settings)
        for col in range(5):
            acquisition = strategy.next_acquisition()
            if col == 3 and middle == "empty":  # glass beside it: looked at, tissue seen
                assert acquisition is not None and is_look(acquisition)
                strategy.record(acquisition, Measurement(None))
                acquisition = strategy.next_acquisition()
            assert acquisition is not None and acquisition.col == col  # one stack a tile
            if col == 2 and middle == "empty":
                outcome = strategy.record(acquisition, empty)
                assert not outcome.accepted
                assert outcome.posterior_um == outcome.prior_um
                assert outcome.posterior_sigma_um == outcome.prior_sigma_um
            else:
                strategy.record(acquisition, Measurement(3.0 if col == 2 else 1.0, SIGMA_UM))
        maps[middle] = strategy.focus_map()
    # the tissue around the empty tile sits at 1 um: the next tile is predicted there, where
    # a measurement of 3 um in the middle pulls its prediction up
    assert maps["empty"].prior_um[0, 3] == pytest.approx(1.0, abs=0.1)
    assert maps["measured"].prior_um[0, 3] > maps["empty"].prior_um[0, 3] + 0.5


def test_the_choice_between_peaks_survives_the_api_and_the_store() -> None:
    measurement = multi_peak(1.0, 4.0, 0.8)
    acquisition = registry.create("kf-2d", default_settings(ScanGrid(2, 2))).next_acquisition()
    assert acquisition is not None
    body = to_api.measurement_in(acquisition, measurement)
    assert to_domain.measurement(api.MeasurementIn.model_validate_json(body.model_dump_json())) == (
        measurement
    )
    assert measurement_of(measurement_record(measurement)) == measurement
    # a record of a measurement without them (as written before) reads back as it was
    record = measurement_record(Measurement(1.0, SIGMA_UM))
    assert set(record) == {"z_um", "sigma_um", "flags"}
    assert measurement_of(record) == Measurement(1.0, SIGMA_UM)
    with pytest.raises(ValueError, match="chosen probability"):
        Measurement(1.0, SIGMA_UM, chosen_probability=1.5)


EMPTY = Measurement(None, flags=frozenset({FocusFlag.FLAT, FocusFlag.EMPTY}))


@pytest.mark.parametrize("name", ["kf-2d", "kf-2d-lean"])
def test_a_tile_in_a_region_of_glass_is_looked_at_with_one_frame(name: str) -> None:
    settings = default_settings(ScanGrid(1, 6), start_z_um=0.0, start_sigma_um=0.5)
    strategy = registry.create(name, settings)
    assert isinstance(strategy, SerpentineFilter)
    stack = strategy.next_acquisition()  # the first tile of glass is found by a stack
    assert stack is not None and stack.col == 0 and stack.z.n_frames > 1
    strategy.record(stack, EMPTY)
    for col in (1, 2):  # glass is all the scan has seen beside them
        look = strategy.next_acquisition()
        assert look is not None and look.col == col and look.measure
        assert (look.z.n_frames, look.purpose) == (1, Purpose.SCAN)
        assert look.z.center_um == look.predicted_um
        outcome = strategy.record(look, EMPTY)  # nothing in view: imaged there, one frame
        assert outcome.posterior_um == outcome.prior_um == strategy.map.z_used_um[0, col]
    assert strategy.empty[0, :3].all()
    look = strategy.next_acquisition()
    assert look is not None and look.col == 3 and look.z.n_frames == 1
    assert not strategy.record(look, Measurement(None)).accepted  # something in view
    stack = strategy.next_acquisition()
    assert stack is not None and stack.col == 3 and stack.z.n_frames > 1
    assert stack.purpose is Purpose.SCAN
    outcome = strategy.record(stack, Measurement(look.z.center_um + 0.01, SIGMA_UM))
    assert outcome.accepted
    # the look's frame is one of the tile's: the one nearest its focus here
    assert strategy.map.z_used_um[0, 3] == look.z.center_um
    assert not strategy.empty[0, 3]


def test_a_field_found_empty_alone_makes_no_look() -> None:
    """A sparse field among tissue: glass is not half of what its neighbours saw."""
    strategy = registry.create("kf-2d", default_settings(ScanGrid(3, 3)))
    for col in (0, 1, 2):  # tissue in the first row
        stack = strategy.next_acquisition()
        assert stack is not None and stack.col == col
        assert strategy.record(stack, Measurement(stack.predicted_um, SIGMA_UM)).accepted
    stack = strategy.next_acquisition()
    assert stack is not None and (stack.row, stack.col) == (1, 2)
    strategy.record(stack, EMPTY)  # beside it: three tissue tiles scanned above
    for col in (1, 0):  # beside one glass tile and three, then two, tissue tiles
        following = strategy.next_acquisition()
        assert following is not None and (following.row, following.col) == (1, col)
        assert following.z.n_frames > 1
        strategy.record(following, Measurement(following.predicted_um, SIGMA_UM))


def test_glass_is_half_at_least_of_what_the_scanned_neighbours_showed() -> None:
    empty, scanned = np.zeros((3, 4), dtype=bool), np.zeros((3, 4), dtype=bool)
    scanned[0] = True
    empty[0, :2] = True  # the first row: glass, glass, tissue, tissue
    assert in_glass(empty, scanned, Tile(1, 0))  # two of two
    assert in_glass(empty, scanned, Tile(1, 1))  # two of three
    assert not in_glass(empty, scanned, Tile(1, 2))  # one of three
    assert not in_glass(empty, scanned, Tile(1, 3))  # glass two tiles away
    assert not in_glass(empty, scanned, Tile(2, 0))  # nothing scanned beside it


def test_a_row_of_glass_along_tissue_is_looked_at_from_its_third_tile() -> None:
    strategy = registry.create("kf-2d", default_settings(ScanGrid(2, 4)))
    for col in range(4):  # tissue in the first row
        stack = strategy.next_acquisition()
        assert stack is not None and stack.col == col
        strategy.record(stack, Measurement(stack.predicted_um, SIGMA_UM))
    for col in (3, 2):  # glass below it, by a stack each: more tissue than glass beside them
        stack = strategy.next_acquisition()
        assert stack is not None and (stack.row, stack.col) == (1, col)
        assert stack.z.n_frames > 1
        strategy.record(stack, EMPTY)
    look = strategy.next_acquisition()  # the last two tiles imaged were glass
    assert look is not None and (look.row, look.col) == (1, 1) and is_look(look)
