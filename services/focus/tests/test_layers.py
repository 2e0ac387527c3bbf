"""Two layers under one top (`layers`): a top broader than the slide's widens the sigma."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_focus.curve_model import CurveModel
from focustrack_focus.layers import MIN_TOPS, layers_sigma_um, learn_top, top_width_um
from focustrack_focus.pipeline import FocusSettings, focus_from_curve

Z_UM = np.arange(-2.0, 2.01, 0.5)
WIDTH_UM = 1.5


def top(centre_um: float = 0.0, width_um: float = WIDTH_UM) -> np.ndarray:
    return np.exp(-0.5 * (Z_UM - centre_um) ** 2 / width_um**2)


def two_layers(apart_um: float) -> np.ndarray:
    return top(-apart_um / 2) + top(apart_um / 2)


def learnt() -> list[float]:
    widths: list[float] = []
    for centre_um in np.linspace(-0.3, 0.3, MIN_TOPS):
        learn_top(widths, Z_UM, top(centre_um), float(centre_um), frozenset())
    return widths


def test_a_top_is_as_wide_as_its_gaussian() -> None:
    assert top_width_um(Z_UM, top(0.2), 0.2) == pytest.approx(WIDTH_UM)
    assert top_width_um(Z_UM, top(), 0.0) == pytest.approx(WIDTH_UM)
    assert top_width_um(Z_UM, -top(), 0.0) is None  # scores not positive: no top
    assert top_width_um(Z_UM, 2.0 - top(), 0.0) is None  # a dip


def test_two_layers_under_one_top_widen_the_sigma_by_at_least_half_their_distance() -> None:
    widths = learnt()
    assert len(widths) == MIN_TOPS
    assert layers_sigma_um(widths, Z_UM, top(), 0.0) == 0.0  # one layer
    assert layers_sigma_um(widths, Z_UM, two_layers(1.5), 0.0) == 0.0  # hardly broader
    # 2.8 um apart, each 1.4 um from the vertex: a top nearly flat
    assert 1.4 <= layers_sigma_um(widths, Z_UM, two_layers(2.8), 0.0) < 6.0
    # too few tops yet: nothing to compare with
    assert layers_sigma_um(widths[:-1], Z_UM, two_layers(2.8), 0.0) == 0.0


def test_only_clean_single_tops_are_learnt() -> None:
    widths = learnt()
    learn_top(widths, Z_UM, top(width_um=5.0), 0.0, frozenset({FocusFlag.MULTI_PEAK}))
    learn_top(widths, Z_UM, two_layers(2.8), 0.0, frozenset())  # read as two layers
    learn_top(widths, Z_UM, top(), None, frozenset())
    assert widths == learnt()


def test_the_service_reads_a_fold_with_a_wider_sigma() -> None:
    curve = CurveModel(top_widths_um=learnt())
    settings = FocusSettings()
    fold = focus_from_curve(Z_UM, 1.0 + two_layers(2.8), settings, curve=curve)
    alone = focus_from_curve(Z_UM, 1.0 + two_layers(2.8), settings)
    assert fold.best_z_um == alone.best_z_um
    assert fold.sigma_um is not None and alone.sigma_um is not None
    assert fold.sigma_um > alone.sigma_um + 1.0
    single = focus_from_curve(Z_UM, 1.0 + top(), settings, curve=curve)
    assert single.sigma_um == focus_from_curve(Z_UM, 1.0 + top(), settings).sigma_um


def test_beside_a_tile_read_as_two_layers_a_less_broad_top_is_two_layers_too() -> None:
    """A fold is a band: beside a tile read as two layers, a top 1.5 to 2 times the slide's
    (a short stack's noisy width of a fold tile) is read as two layers; away from it, not."""
    widths = learnt()
    broad = top(width_um=1.75 * WIDTH_UM)
    assert layers_sigma_um(widths, Z_UM, broad, 0.0) == 0.0
    assert layers_sigma_um(widths, Z_UM, broad, 0.0, beside_layers=True) > 1.0
    assert layers_sigma_um(widths, Z_UM, top(), 0.0, beside_layers=True) == 0.0  # one layer
    curve = CurveModel(top_widths_um=widths)
    assert not learn_top(widths, Z_UM, broad, 0.0, frozenset())  # learnt as a clean top
    assert learn_top(widths, Z_UM, two_layers(2.8), 0.0, frozenset())
    assert learn_top(widths, Z_UM, broad, 0.0, frozenset(), beside_layers=True)
    curve.layered_tiles.add((4, 5))
    assert curve.beside_layers((5, 6)) and curve.beside_layers((4, 5))
    assert not curve.beside_layers((6, 5))
