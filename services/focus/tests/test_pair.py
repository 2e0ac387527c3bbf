"""A pair of frames read with the slide's learnt curve: their scores' ratio places the peak."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import PAIR_REACH_UM, FocusFlag
from focustrack_focus.curve_model import CurveModel, lorentzian
from focustrack_focus.pair import pair_mu_um, read_pair
from focustrack_focus.pipeline import FocusSettings, FrameByFrame, pair_result

GAMMA_UM, BACKGROUND = 3.0, 0.2
PAIR_UM = np.array([4.75, 5.25])  # one z step (0.5 um) apart about 5 um


def _model() -> CurveModel:
    return CurveModel(
        gammas_um=[GAMMA_UM], backgrounds=[BACKGROUND], noise_shares=[0.002],
        misfit_shares=[0.01],
    )  # fmt: skip


def _scores(mu_um: float, height: float = 7.0) -> np.ndarray:
    return height * lorentzian(PAIR_UM, mu_um, GAMMA_UM, BACKGROUND)


@pytest.mark.parametrize("offset_um", [-1.2, -0.6, -0.1, 0.0, 0.2, 0.7, 1.2])
def test_the_ratio_of_two_frames_places_the_peak_whatever_the_tiles_contrast(
    offset_um: float,
) -> None:
    for height in (0.5, 7.0, 300.0):
        fit = read_pair(PAIR_UM, _scores(5.0 + offset_um, height), _model())
        assert fit.is_observation and not fit.flags
        assert fit.z_um == pytest.approx(5.0 + offset_um, abs=1e-3)
    # the doubt grows away from the frames (the ratio flattens) and with the widths' spread
    near = read_pair(PAIR_UM, _scores(5.0), _model())
    far = read_pair(PAIR_UM, _scores(6.2), _model())
    assert near.sigma_um is not None and far.sigma_um is not None
    assert 0 < near.sigma_um < far.sigma_um < 1.0


def test_a_peak_beyond_the_pairs_reach_is_an_edge_that_way() -> None:
    above = read_pair(PAIR_UM, _scores(PAIR_UM[1] + PAIR_REACH_UM + 0.5), _model())
    assert above.flags == {FocusFlag.EDGE_HIGH} and not above.is_observation
    below = read_pair(PAIR_UM, _scores(PAIR_UM[0] - PAIR_REACH_UM - 0.5), _model())
    assert below.flags == {FocusFlag.EDGE_LOW}
    # noise beyond the ratio's extremes: off the branch, that way
    assert pair_mu_um(PAIR_UM, np.array([1.0, 100.0]), GAMMA_UM, BACKGROUND) == np.inf
    # far away both frames see the background alone, as a peak midway would make them
    # equal: a pair is no search (the estimator takes one only where its prediction is close)
    far = read_pair(PAIR_UM, _scores(-20.0), _model())
    assert far.z_um is not None and abs(far.z_um - 5.0) < PAIR_REACH_UM
    assert read_pair(PAIR_UM, np.array([0.0, 1.0]), _model()).flags == {FocusFlag.FLAT}


def test_a_pair_reaches_the_focus_service_only_once_the_slides_curve_is_learnt() -> None:
    settings = FocusSettings()
    with pytest.raises(ValueError, match="at least 3"):
        FrameByFrame(PAIR_UM, settings)
    stack = FrameByFrame(PAIR_UM[::-1], settings, pairs=True)  # frames in any order
    rng = np.random.default_rng(0)
    textured = rng.uniform(0, 255, (2, 64, 64)).astype(np.float32)
    for index in range(2):
        stack.add(index, textured[index])
    assert stack.complete
    # read without a curve: an edge towards the higher frame (a retry continues that way)
    scores = _scores(5.6)
    without = pair_result(PAIR_UM, scores, np.inf, settings, 0.0)
    assert without.flags == {FocusFlag.EDGE_HIGH} and without.best_z_um == PAIR_UM[1]
    with_curve = pair_result(PAIR_UM, scores, np.inf, settings, 0.0, _model())
    assert with_curve.best_z_um == pytest.approx(5.6, abs=1e-3) and not with_curve.flags
    # nothing in view: flat and empty, whatever the curve
    empty = pair_result(PAIR_UM, scores, 0.0, settings, 0.0, _model())
    assert empty.flags == {FocusFlag.FLAT, FocusFlag.EMPTY} and empty.best_z_um is None
