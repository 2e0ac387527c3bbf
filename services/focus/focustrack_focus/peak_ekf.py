"""Best focus from a stream of raw metric samples: an extended Kalman filter on the curve model.

When the stage moves through z while the camera streams, each frame is one focus
metric sample at a known z. `find_peak` (peak.py) waits for a curve that brackets
the peak and fits a parabola in log(score) around its best frame: a linear
least-squares fit. Here each sample updates an extended Kalman filter (as the EKF
seed compares one with a linear filter; iterated: `PeakEKF`) whose state is
[mu_um, log A] and whose measurement is the curve model of `curve_model` (the slide's
Lorentzian on a background, width gamma and background b learnt from full curves),
in log space:

    log s = log A + log(b + (1 - b) / (1 + ((z - mu) / gamma)^2)) + e,

e the relative score noise (`noise_share`). The model is nonlinear in mu, so the
filter linearises it at each sample (the Jacobian below). Known shape makes one
flank informative: the filter locates the peak from samples on its way up, before
the top is passed, and says how sure it is (`sigma_um`). `stream_peak` stops as soon
as that sigma is below `stop_sigma_um`. Heights in um, scores positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from focustrack_focus.curve_model import lorentzian

#: Prior std of log A: the height is learnt from the first samples.
LOG_HEIGHT_SIGMA = 3.0

#: Gauss-Newton steps of each iterated update (the first is the plain EKF's).
ITERATIONS = 5


@dataclass(frozen=True)
class StreamFit:
    """Where a stream's peak is (um), how sure (um), and after how many samples."""

    z_um: float
    sigma_um: float
    n_frames: int
    converged: bool  # sigma fell below the stop before the samples ran out


def _log_shape(z_um: float, mu_um: float, gamma_um: float, background: float) -> float:
    return math.log(float(lorentzian(np.array([z_um]), mu_um, gamma_um, background)[0]))


def _d_log_shape_d_mu(z_um: float, mu_um: float, gamma_um: float, background: float) -> float:
    """d/dmu of log(b + (1 - b) / (1 + u^2)), u = (z - mu) / gamma."""
    u = (z_um - mu_um) / gamma_um
    peak = 1.0 / (1.0 + u * u)
    shape = background + (1.0 - background) * peak
    # d peak / d mu = 2 u / gamma * peak^2
    return (1.0 - background) * 2.0 * u / gamma_um * peak * peak / shape


class PeakEKF:
    """The iterated EKF of one tile's stream: state [mu_um, log height] (module docstring).

    Each update is linearised again at its own estimate (`ITERATIONS` Gauss-Newton steps
    on the prior and the sample: the iterated EKF): on a flank far from the prior's mu a
    single linearisation overshoots.
    """

    def __init__(
        self,
        mu_um: float,
        sigma_um: float,
        gamma_um: float,
        background: float,
        noise_share: float,
    ) -> None:
        if not (sigma_um > 0 and gamma_um > 0 and 0 <= background < 1 and noise_share > 0):
            raise ValueError("sigma, gamma and the noise share must be positive, b in [0, 1)")
        self.gamma_um, self.background = gamma_um, background
        self.x = np.array([mu_um, 0.0])  # log height: set by the first sample
        self.P = np.diag([sigma_um**2, LOG_HEIGHT_SIGMA**2])
        self.R = noise_share**2
        self._started = False

    @property
    def mu_um(self) -> float:
        return float(self.x[0])

    @property
    def sigma_um(self) -> float:
        return math.sqrt(max(float(self.P[0, 0]), 0.0))

    def update(self, z_um: float, score: float) -> None:
        """Take one sample: the metric's `score` (> 0) at `z_um`."""
        if not score > 0:
            raise ValueError(f"scores must be positive, got {score}")
        gamma, b = self.gamma_um, self.background
        if not self._started:  # the height's first guess: this sample under the prior's mu
            self.x[1] = math.log(score) - _log_shape(z_um, self.mu_um, gamma, b)
            self._started = True
        x0, P0, y = self.x, self.P, math.log(score)
        x = x0.copy()
        for _ in range(ITERATIONS):
            H = np.array([_d_log_shape_d_mu(z_um, float(x[0]), gamma, b), 1.0])
            predicted = float(x[1]) + _log_shape(z_um, float(x[0]), gamma, b)
            gain = P0 @ H / (H @ P0 @ H + self.R)
            x = x0 + gain * (y - predicted - H @ (x0 - x))
        self.x = x
        self.P = (np.eye(2) - np.outer(gain, H)) @ P0


def stream_peak(
    z_um: np.ndarray,
    scores: np.ndarray,
    *,
    mu_um: float,
    sigma_um: float,
    gamma_um: float,
    background: float,
    noise_share: float,
    stop_sigma_um: float,
    min_frames: int = 3,
) -> StreamFit:
    """Run a `PeakEKF` over the samples (n,) in order (z ascending), from the prior
    N(mu_um, sigma_um^2); stop once its sigma is below `stop_sigma_um` (after at least
    `min_frames`) and the samples have come within half a width (gamma / 2) of its mu:
    a mu far ahead of every sample rests on the model's flank alone, where a real curve
    departs from it most (second peaks, sloping backgrounds)."""
    ekf = PeakEKF(mu_um, sigma_um, gamma_um, background, noise_share)
    for n, (z, s) in enumerate(zip(z_um, scores, strict=True), start=1):
        ekf.update(float(z), float(s))
        reached = float(z) >= ekf.mu_um - gamma_um / 2.0
        if n >= min_frames and reached and ekf.sigma_um < stop_sigma_um:
            return StreamFit(ekf.mu_um, ekf.sigma_um, n, True)
    return StreamFit(ekf.mu_um, ekf.sigma_um, len(z_um), False)
