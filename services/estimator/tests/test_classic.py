"""The classic strategies: they complete, image as many frames as they should, interpolate right."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag, Measurement, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import family_spec, generate_surfaces
from focustrack_estimator import classic, registry
from focustrack_estimator.replay import replay
from focustrack_estimator.strategy import Strategy

NAMES = ["af-every-tile", "tile-skip", "survey-bilinear", "survey-spline", "survey-delaunay"]
WIDE = 41  # frames of the default policy's widest stack


def _plane(rows: int, cols: int) -> np.ndarray:
    row, col = np.indices((rows, cols))
    return 1.5 + 0.3 * row - 0.2 * col


def test_registered_with_their_defaults() -> None:
    assert set(classic.STRATEGIES) == set(NAMES)
    assert all(name in registry.STRATEGIES for name in NAMES)
    assert registry.parameters("af-every-tile") == {}
    assert registry.parameters("tile-skip") == {"every": 2}
    assert set(registry.parameters("survey-delaunay")) == {"n_survey"}
    with pytest.raises(ValueError, match=r"unknown parameter 'n_points'.*known: n_survey"):
        registry.create("survey-spline", default_settings(ScanGrid(20, 20)), {"n_points": 9})


@pytest.mark.parametrize("name", NAMES)
def test_each_strategy_completes_on_a_noisy_map(name: str) -> None:
    truth = generate_surfaces(family_spec("standard"), 1, seed=11)[0]
    measured = truth + np.random.default_rng(11).normal(0.0, 1.5, truth.shape)
    strategy = registry.create(name, default_settings(ScanGrid(20, 20)))
    run = replay(strategy, truth, measured)
    assert strategy.next_acquisition() is None
    focus_map = run.focus_map
    assert np.all(np.isnan(focus_map.prior_um))  # no strategy here predicts
    assert np.all(np.isfinite(focus_map.posterior_um)) and np.all(np.isfinite(focus_map.z_used_um))
    assert np.mean(np.abs(focus_map.posterior_um - truth)) < 1.5


def test_image_counts() -> None:
    truth = _plane(20, 20)
    settings = default_settings(ScanGrid(20, 20))

    def images(strategy: Strategy) -> int:
        return replay(strategy, truth, truth).n_images

    assert images(registry.create("af-every-tile", settings)) == 400 * WIDE
    assert images(registry.create("tile-skip", settings)) == 200 * WIDE + 200  # thesis: 200
    assert images(registry.create("tile-skip", settings, {"every": 3})) == 134 * WIDE + 266
    for name, n_survey in [
        ("survey-bilinear", 49),
        ("survey-spline", 36),
        ("survey-delaunay", 100),
    ]:
        strategy = registry.create(name, settings, {"n_survey": n_survey})
        assert images(strategy) == n_survey * WIDE + 400


def test_tile_skip_reuses_the_last_measured_height() -> None:
    truth = _plane(3, 4)
    run = replay(
        registry.create("tile-skip", default_settings(ScanGrid(3, 4)), {"every": 3}), truth, truth
    )
    grid = ScanGrid(3, 4)
    for position, tile in enumerate(grid.serpentine):
        focused = grid.serpentine[position - position % 3]
        assert run.focus_map.posterior_um[tile.row, tile.col] == truth[focused.row, focused.col]


@pytest.mark.parametrize(
    ("name", "n_survey"), [("survey-bilinear", 16), ("survey-spline", 25), ("survey-delaunay", 16)]
)
def test_survey_interpolation_is_exact_on_a_plane(name: str, n_survey: int) -> None:
    truth = _plane(11, 13)
    settings = default_settings(ScanGrid(11, 13))
    run = replay(registry.create(name, settings, {"n_survey": n_survey}), truth, truth)
    assert np.allclose(run.focus_map.posterior_um, truth, atol=1e-9)
    assert np.allclose(run.focus_map.z_used_um, truth, atol=1e-9)


def test_survey_pass_comes_first_then_single_frames_in_serpentine_order() -> None:
    grid = ScanGrid(5, 6)
    strategy = registry.create("survey-delaunay", default_settings(grid), {"n_survey": 9})
    truth = _plane(5, 6)
    acquisitions = []
    while (acquisition := strategy.next_acquisition()) is not None:
        acquisitions.append(acquisition)
        strategy.record(acquisition, Measurement(float(truth[acquisition.row, acquisition.col])))
    survey, scan = acquisitions[:9], acquisitions[9:]
    assert all(a.purpose is Purpose.SURVEY and a.measure and a.z.n_frames == WIDE for a in survey)
    # A short serpentine over the 3x3 survey grid, its outer points on the map's edges.
    assert [(a.row, a.col) for a in survey] == [
        (0, 0), (0, 2), (0, 5), (2, 5), (2, 2), (2, 0), (4, 0), (4, 2), (4, 5),
    ]  # fmt: skip
    assert [(a.row, a.col) for a in scan] == [(t.row, t.col) for t in grid.serpentine]
    assert all(a.purpose is Purpose.SCAN and not a.measure and a.z.n_frames == 1 for a in scan)
    assert all(a.predicted_um is None for a in acquisitions)


def test_survey_axes() -> None:
    rows, cols = classic.survey_axes(36, 20, 20)
    assert len(rows) == len(cols) == 6 and rows[0] == cols[0] == 0 and rows[-1] == cols[-1] == 19
    rows, cols = classic.survey_axes(50, 10, 40)  # follows the aspect ratio
    assert (len(rows), len(cols)) == (4, 12)
    rows, cols = classic.survey_axes(1000, 4, 5)  # never more than every tile
    assert list(rows) == [0, 1, 2, 3] and list(cols) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="at least one survey point"):
        classic.survey_axes(0, 5, 5)
    with pytest.raises(ValueError, match="needs at least 4 survey points per axis"):
        registry.create("survey-spline", default_settings(ScanGrid(20, 20)), {"n_survey": 9})


def test_an_edge_peak_is_chased_and_a_hopeless_tile_given_up() -> None:
    strategy = registry.create("af-every-tile", default_settings(ScanGrid(1, 2), start_z_um=0.0))
    first = strategy.next_acquisition()
    assert first is not None
    outcome = strategy.record(first, Measurement(None, flags=frozenset({FocusFlag.EDGE_LOW})))
    retry = strategy.next_acquisition()
    assert not outcome.accepted and retry is not None and retry.purpose is Purpose.RETRY
    assert (retry.row, retry.col) == (0, 0) and retry.z.low_um < first.z.low_um < retry.z.high_um

    # Far beyond any stack: after MAX_RETRIES blocks the tile is imaged at the start height.
    truth = np.array([[1000.0, 1000.0]])
    run = replay(registry.create("af-every-tile", default_settings(ScanGrid(1, 2))), truth, truth)
    assert run.n_images == 2 * (1 + classic.MAX_RETRIES) * WIDE
    assert np.all(run.focus_map.z_used_um == 0.0) and not any(o.accepted for o in run.outcomes)


def test_delaunay_fills_beyond_the_hull_from_the_nearest_survey_point() -> None:
    grid = ScanGrid(5, 5)
    strategy = registry.create("survey-delaunay", default_settings(grid), {"n_survey": 9})
    truth = _plane(5, 5)
    corners = {(0, 0), (0, 4), (4, 0), (4, 4)}
    while (acquisition := strategy.next_acquisition()) is not None:
        tile = (acquisition.row, acquisition.col)
        if acquisition.purpose is Purpose.SURVEY and tile in corners:
            measurement = Measurement(None, flags=frozenset({FocusFlag.FLAT}))  # an empty field
        else:
            measurement = Measurement(float(truth[tile]))
        strategy.record(acquisition, measurement)
    posterior = strategy.focus_map().posterior_um
    # The five measured points (a diamond) interpolate exactly inside; corners take a neighbour.
    inside = [(2, 2), (1, 2), (2, 3)]
    assert np.allclose([posterior[t] for t in inside], [truth[t] for t in inside])
    assert posterior[0, 0] in {truth[0, 2], truth[2, 0]}
    assert np.all(np.isfinite(posterior))


def test_grid_survey_fills_a_missing_node_from_its_nearest_neighbour() -> None:
    strategy = registry.create("survey-bilinear", default_settings(ScanGrid(3, 3)), {"n_survey": 9})
    while (acquisition := strategy.next_acquisition()) is not None:
        z_um = None if (acquisition.row, acquisition.col) == (1, 1) else 2.0
        flags = frozenset({FocusFlag.FLAT}) if z_um is None else frozenset()
        strategy.record(acquisition, Measurement(z_um, flags=flags))
    assert np.all(strategy.focus_map().posterior_um == 2.0)
