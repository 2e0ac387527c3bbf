"""Two frames read with the slide's learnt curve: the ratio of their scores places the peak.

With the curve's shape known (`curve_model.CurveModel`: width gamma and background share
b), the height A is the only thing a tile adds, and the ratio of two frames' scores
cancels it. For a Gaussian curve log(s(z+) / s(z-)) is linear in the peak's offset from
their middle (log s = log A - (z - mu)^2 / (2 w^2), so the log-ratio is
(z+ - z-) (mu - (z+ + z-) / 2) / w^2); for the model's Lorentzian on a background the
ratio

    r(mu) = g(z+; mu) / g(z-; mu),   g(z; mu) = b + (1 - b) / (1 + ((z - mu) / gamma)^2),

rises from 1 (the peak far below) to a maximum (the peak about a width above the pair)
and falls back to 1: it is one-to-one on the branch between its minimum and its maximum,
and that branch holds the peak where the prediction is not off by a curve's width. The
peak is read there (`read_pair`): a measurement where it lies within `PAIR_REACH_UM` of
the frames, with the sigma of the short stacks' model reading (the score noise and the
curve's misfit propagated to mu, `curve_model.information_sigma_um`, and how far mu moves
when the width is one spread either way); beyond that reach, or off the branch, an edge
flag that way (the estimator's retry continues there). Two frames say nothing of the
curve's own shape: no second peak, no top broader than the slide's (a fold), so the
caller asks for a pair only where the prediction is close (the lean rule's short stack).
Heights in um.
"""

from __future__ import annotations

import math

import numpy as np

from focustrack_core.domain import PAIR_REACH_UM, FocusFlag
from focustrack_focus.curve_model import CurveModel, information_sigma_um, lorentzian
from focustrack_focus.peak import PeakFit

#: Points of the grid on which the ratio's branch is found (over +/- BRANCH_WIDTHS widths).
BRANCH_POINTS = 801
BRANCH_WIDTHS = 4.0


def _log_ratio(z_um: np.ndarray, mu_um: np.ndarray, gamma_um: float, b: float) -> np.ndarray:
    """log(g(z+; mu) / g(z-; mu)) for each mu (m,): z_um (2,) ascending. The model depends
    on z - mu alone through its square: g(z; mu) = g(mu; z), evaluated over the mu grid."""
    high = lorentzian(mu_um, float(z_um[1]), gamma_um, b)
    low = lorentzian(mu_um, float(z_um[0]), gamma_um, b)
    return np.log(high) - np.log(low)


def pair_mu_um(z_um: np.ndarray, scores: np.ndarray, gamma_um: float, b: float) -> float | None:
    """The peak (um) whose model gives the pair's score ratio, on the ratio's one-to-one
    branch; +/-inf where the ratio lies beyond the branch's ends (the peak is about a width
    or more below / above), None where the scores are not positive.

    z_um (2,) ascending, scores (2,).
    """
    if not (scores[0] > 0 and scores[1] > 0):
        return None
    middle_um = float(z_um.mean())
    grid = middle_um + np.linspace(-1.0, 1.0, BRANCH_POINTS) * BRANCH_WIDTHS * gamma_um
    curve = _log_ratio(z_um, grid, gamma_um, b)
    low, high = int(np.argmin(curve)), int(np.argmax(curve))  # the branch: rising between
    measured = math.log(scores[1] / scores[0])
    if measured <= curve[low]:
        return -math.inf
    if measured >= curve[high]:
        return math.inf
    branch, values = grid[low : high + 1], curve[low : high + 1]
    return float(np.interp(measured, values, branch))


def read_pair(
    z_um: np.ndarray, scores: np.ndarray, model: CurveModel, *, floor_sigma_um: float = 0.0
) -> PeakFit:
    """The peak of a pair (z (2,) ascending, scores (2,)) read with the slide's ready curve
    `model` (module docstring): a measurement within PAIR_REACH_UM of the frames, else an
    edge flag towards it (FLAT where the scores are not positive). `floor_sigma_um` is
    added to the sigma, as to a short stack's (`curve_model.fit_short_stack`)."""
    gamma_um, b = model.gamma_um, model.background
    mu_um = pair_mu_um(z_um, scores, gamma_um, b)
    if mu_um is None:
        return PeakFit(None, None, frozenset({FocusFlag.FLAT}))
    low_um, high_um = float(z_um[0]), float(z_um[1])
    if mu_um < low_um - PAIR_REACH_UM:
        return PeakFit(low_um, None, frozenset({FocusFlag.EDGE_LOW}))
    if mu_um > high_um + PAIR_REACH_UM:
        return PeakFit(high_um, None, frozenset({FocusFlag.EDGE_HIGH}))
    misfit_sigma_um = information_sigma_um(z_um, mu_um, gamma_um, b, model.misfit_share)
    spread_um = model.gamma_spread_um
    shape_sigma_um = 0.0
    if spread_um > 0:
        readings = [
            pair_mu_um(z_um, scores, width_um, b)
            for width_um in (gamma_um + spread_um, max(gamma_um - spread_um, 1e-3))
        ]
        finite = [mu for mu in readings if mu is not None and math.isfinite(mu)]
        # a width at which the ratio leaves the branch: the reading is that width's doubt
        shape_sigma_um = abs(finite[0] - finite[1]) / 2.0 if len(finite) == 2 else PAIR_REACH_UM
    sigma_um = math.hypot(misfit_sigma_um, shape_sigma_um, floor_sigma_um)
    return PeakFit(mu_um, sigma_um, frozenset(), chosen_probability=1.0)
