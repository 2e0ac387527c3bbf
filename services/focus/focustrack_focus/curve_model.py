"""The through-focus curve of a slide, learnt online, and short stacks (3 frames) read with it.

A focus curve's shape (its width and how much of it is background) belongs to
the slide, the objective and the metric, not to the tile. Learnt from the
first tiles' full stacks, it lets 3 frames around a prediction locate the peak
anywhere between the outer two, where the model-free reading (`peak.find_peak`)
needs the middle frame to be the highest.

Model (a Lorentzian on a background; the simulator's normalised-variance curve
is within 5% of it over +/- 5 um):

    s(z) = A (b + (1 - b) / (1 + ((z - mu) / gamma)^2)),

gamma_um the half width at half height of the peak above the background, b
the background's share of the peak, A the height (per tile: it follows the
specimen's contrast). `CurveModel.learn` fits (mu, A, gamma, b) to each full
stack with a clean single peak (`fit_curve`) and keeps the medians of gamma, b,
the relative score noise and the fit's relative misfit of the last
`MAX_CURVES`; it is ready after `MIN_CURVES` (one).

A short stack (`fit_short_stack`): where the model-free reading brackets the
peak, its z stands and the model gives the sigma three frames cannot (their
score noise, learnt from the full stacks, propagated to the peak). Where it
saw an edge, the model is fitted for (mu, A) with gamma and b fixed: A is
linear (profiled out), mu by a grid then a bounded minimisation. Its sigma is
the sum in quadrature of
- misfit: the curve's departure from the model (noise included) propagated to
  mu (Gauss-Newton, A profiled out: share^2 / |dg/dmu orthogonal to g|^2);
- shape: how far mu moves when gamma is one spread (MAD) of the learnt widths
  either way (a tile's curve is not the slide's median one).
A peak the model puts inside the stack is a measurement; one outside it, or
frames that disagree with the model (a residual above `MAX_RESIDUAL_SIGMAS`
misfits), leave the edge flag, and the retry policy (in the estimator) takes
over.
Heights in um, shapes (n,).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from focustrack_core.domain import CURVE_LEARN_FRAMES, CURVE_SPREAD_CURVES, FocusFlag
from focustrack_focus.curve_checks import between_maxima
from focustrack_focus.noise_bound import score_noise
from focustrack_focus.peak import MAD_TO_SIGMA, PeakFit, PeakMode

#: Stacks of at most this many frames are read with the model (when it is ready).
SHORT_MAX_FRAMES = 3
#: Full stacks a model needs before it reads short ones, and the most it remembers. One is
#: enough: a lean scan takes a full (or coarse) stack on its first tile and few after it.
MIN_CURVES = 1
MAX_CURVES = 50
#: Until CURVE_SPREAD_CURVES curves, the spread of the widths is taken as this share of the
#: width (a median absolute deviation of fewer curves says little).
DEFAULT_WIDTH_SPREAD = 0.15
#: A short stack whose fit leaves more than this many noise sigmas (rms) disagrees.
MAX_RESIDUAL_SIGMAS = 4.0
#: The relative score noise never counts as less than this (a noiseless simulator curve
#: would otherwise give a sigma of zero).
MIN_NOISE_SHARE = 1e-3


def as_modelled(
    z_um: np.ndarray, scores: np.ndarray, mode: PeakMode
) -> tuple[np.ndarray, np.ndarray]:
    """A curve, z (n,) in um ascending and scores (n,), as the model reads it: a peak.

    MAX: as it is. VALLEY (an unstained specimen): the frames from one of the valley's
    maxima to the other (`curve_checks.between_maxima`; all of them where it has none), each
    score's reciprocal. Near focus a phase object's contrast grows as the square of the
    defocus, s = s0 + k (z - mu)**2, whose reciprocal is this model's peak: a Lorentzian of
    half width sqrt(s0 / k) on no background. Unlike the curve turned upside down, as
    `peak.find_peak` reads a valley on its own, the reciprocal does not depend on the
    frames' range, so one stack's shape holds for the next. Scores not all above zero (a
    metric that can go negative on noise) are turned upside down all the same: max - s +
    span.
    """
    if mode is PeakMode.MAX:
        return z_um, scores
    z_um, scores = between_maxima(z_um, scores)
    if np.all(scores > 0):
        return z_um, 1.0 / scores
    return z_um, float(scores.max()) - scores + float(scores.max() - scores.min())


def lorentzian(z_um: np.ndarray, mu_um: float, gamma_um: float, background: float) -> np.ndarray:
    """The model's shape for A = 1: b + (1 - b) / (1 + ((z - mu) / gamma)^2), shape of z."""
    return background + (1.0 - background) / (1.0 + ((z_um - mu_um) / gamma_um) ** 2)


@dataclass(frozen=True)
class CurveFit:
    """One full curve's parameters: peak mu (um), height A, width gamma (um), background b;
    the score noise over A (`noise_bound.score_noise`, third differences) and the fit's residual
    std over A (noise and the model's own misfit)."""

    mu_um: float
    height: float
    gamma_um: float
    background: float
    noise_share: float
    misfit_share: float


def fit_curve(z_um: np.ndarray, scores: np.ndarray, mu0_um: float) -> CurveFit | None:
    """Fit the model to a full curve (n,) whose peak is near `mu0_um`; None if it fails."""
    top = float(scores.max())
    if not top > 0:
        return None

    def model(z: np.ndarray, mu: float, height: float, gamma: float, b: float) -> np.ndarray:
        return height * lorentzian(z, mu, gamma, b)

    span_um = float(z_um[-1] - z_um[0])
    from scipy.optimize import curve_fit  # imported on first use: 0.5 s, not at start-up

    try:
        params, _ = curve_fit(
            model,
            z_um,
            scores,
            p0=(mu0_um, top, span_um / 4.0, 0.2),
            bounds=([z_um[0], 0.0, 1e-3, 0.0], [z_um[-1], 10.0 * top, 10.0 * span_um, 0.99]),
            maxfev=2000,
        )
    except (RuntimeError, ValueError):
        return None
    mu, height, gamma, b = (float(p) for p in params)
    residual = scores - model(z_um, mu, height, gamma, b)
    misfit = float(np.sqrt(np.mean(residual**2) * z_um.size / max(z_um.size - 4, 1)))
    noise, _ = score_noise(scores)
    return CurveFit(mu, height, gamma, b, noise / height, misfit / height)


@dataclass
class CurveModel:
    """The slide's curve for one metric, learnt from full stacks (module docstring)."""

    gammas_um: list[float] = field(default_factory=list)
    backgrounds: list[float] = field(default_factory=list)
    noise_shares: list[float] = field(default_factory=list)
    misfit_shares: list[float] = field(default_factory=list)
    #: the widths of the slide's clean tops, um (`layers.learn_top`): any stack, short ones too
    top_widths_um: list[float] = field(default_factory=list)
    #: the tiles (row, col) whose top was read as two layers (`layers`: a fold's band)
    layered_tiles: set[tuple[int, int]] = field(default_factory=set)

    def beside_layers(self, tile: tuple[int, int]) -> bool:
        """Whether `tile` (row, col) or one of the eight around it was read as two layers."""
        return any(
            abs(row - tile[0]) <= 1 and abs(col - tile[1]) <= 1 for row, col in self.layered_tiles
        )

    @property
    def ready(self) -> bool:
        return len(self.gammas_um) >= MIN_CURVES

    @property
    def gamma_um(self) -> float:
        return float(np.median(self.gammas_um))

    @property
    def gamma_spread_um(self) -> float:
        """The spread of the learnt widths (MAD as a std; `DEFAULT_WIDTH_SPREAD` of the width
        until CURVE_SPREAD_CURVES curves)."""
        if len(self.gammas_um) < CURVE_SPREAD_CURVES:
            return DEFAULT_WIDTH_SPREAD * self.gamma_um
        return MAD_TO_SIGMA * float(np.median(np.abs(np.array(self.gammas_um) - self.gamma_um)))

    @property
    def background(self) -> float:
        return float(np.median(self.backgrounds))

    @property
    def noise_share(self) -> float:
        """The score noise over the height (at least MIN_NOISE_SHARE)."""
        return max(float(np.median(self.noise_shares)), MIN_NOISE_SHARE)

    @property
    def misfit_share(self) -> float:
        """How far a tile's curve departs from the model, over the height (noise included)."""
        return max(float(np.median(self.misfit_shares)), self.noise_share)

    def learn(
        self,
        z_um: np.ndarray,
        scores: np.ndarray,
        best_z_um: float | None,
        flags: frozenset[FocusFlag],
    ) -> bool:
        """Learn from a full curve (n,) read (`find_peak`) as one clean peak at best_z_um;
        True if it was used."""
        if z_um.size < CURVE_LEARN_FRAMES or flags or best_z_um is None:
            return False
        inside = int(np.count_nonzero(z_um < best_z_um)), int(np.count_nonzero(z_um > best_z_um))
        if min(inside) < 2:  # the peak needs both flanks
            return False
        curve = fit_curve(z_um, scores, best_z_um)
        if curve is None:
            return False
        for values, value in (
            (self.gammas_um, curve.gamma_um),
            (self.backgrounds, curve.background),
            (self.noise_shares, curve.noise_share),
            (self.misfit_shares, curve.misfit_share),
        ):
            values.append(value)
            del values[:-MAX_CURVES]
        return True


def _profile(z_um: np.ndarray, s: np.ndarray, mu_um: float, gamma_um: float, b: float) -> float:
    """Residual sum of squares at mu with the best height A (linear, profiled out)."""
    g = lorentzian(z_um, mu_um, gamma_um, b)
    height = float(g @ s / (g @ g))
    return float(np.sum((s - height * g) ** 2))


def _fit_mu(z_um: np.ndarray, s: np.ndarray, gamma_um: float, b: float) -> float:
    """The mu (um) of the least-squares fit, searched within one width of the stack."""
    low, high = float(z_um[0]) - gamma_um, float(z_um[-1]) + gamma_um
    grid = np.linspace(low, high, 81)
    best = int(np.argmin([_profile(z_um, s, mu, gamma_um, b) for mu in grid]))
    step = grid[1] - grid[0]
    from scipy.optimize import minimize_scalar  # imported on first use, not at start-up

    result = minimize_scalar(
        lambda mu: _profile(z_um, s, mu, gamma_um, b),
        bounds=(grid[best] - step, grid[best] + step),
        method="bounded",
        options={"xatol": 1e-5},
    )
    return float(result.x)


def information_sigma_um(
    z_um: np.ndarray, mu_um: float, gamma_um: float, b: float, noise_share: float
) -> float:
    """The std of mu from scores with noise `noise_share` x A (Gauss-Newton, A profiled out).

    d g / d mu is made orthogonal to g (the height is fitted too); the information
    on mu is then |dg_perp|^2 / noise_share^2 (A cancels).
    """
    g = lorentzian(z_um, mu_um, gamma_um, b)
    u = (z_um - mu_um) / gamma_um
    dg = (1.0 - b) * 2.0 * u / (gamma_um * (1.0 + u**2) ** 2)
    dg_perp = dg - g * float(dg @ g / (g @ g))
    information = float(dg_perp @ dg_perp) / noise_share**2
    return math.inf if information <= 0 else 1.0 / math.sqrt(information)


def fit_short_stack(
    z_um: np.ndarray,
    scores: np.ndarray,
    model: CurveModel,
    free: PeakFit,
    *,
    floor_sigma_um: float = 0.0,
) -> PeakFit:
    """Read a short stack (n <= SHORT_MAX_FRAMES, sorted by z) with a ready model.

    `free` is the model-free reading (`peak.find_peak`). Where it found the peak
    bracketed (the middle frame highest: Caruana's three-point fit is exact for
    a locally Gaussian peak) its z stands, with the sigma the score noise gives
    (three frames cannot estimate their own noise: `find_peak` then states only its
    sampling floor). Where it saw an edge, the model is fitted: a peak inside the
    stack is a measurement with the model's sigma (noise, misfit and the spread of
    widths), one outside an edge flag that way (the retry policy takes over).
    Where the frames disagree with the model, or `free` found no curve, `free` stands.
    `floor_sigma_um` is added to the model's sigma: what `find_peak` adds to its own
    (the sampling floor and the metric's systematic offset, `peak_floor_sigma_um`). A
    narrow model (a valley's reciprocal is 0.1-0.2 um wide) states sigmas under a
    nanometre without it, finer than any stage moves and than the estimator takes.
    """
    gamma_um, b = model.gamma_um, model.background
    s = np.asarray(scores, dtype=float)
    if free.is_observation and free.z_um is not None and free.sigma_um is not None:
        noise_sigma_um = information_sigma_um(z_um, free.z_um, gamma_um, b, model.noise_share)
        return PeakFit(
            free.z_um,
            math.hypot(free.sigma_um, noise_sigma_um),
            free.flags,
            free.runner_up_z_um,
            free.chosen_probability,
        )
    if not free.flags & {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH}:
        return free  # flat or empty: nothing for the model to read
    mu_um = _fit_mu(z_um, s, gamma_um, b)
    g = lorentzian(z_um, mu_um, gamma_um, b)
    height = float(g @ s / (g @ g))
    residual_rms = math.sqrt(_profile(z_um, s, mu_um, gamma_um, b) / z_um.size)
    if not height > 0 or residual_rms > MAX_RESIDUAL_SIGMAS * model.misfit_share * height:
        return free
    low, high = float(z_um[0]), float(z_um[-1])
    if not low <= mu_um <= high:
        return free  # the model agrees: the peak lies beyond the edge that `free` flagged
    misfit_sigma_um = information_sigma_um(z_um, mu_um, gamma_um, b, model.misfit_share)
    spread = model.gamma_spread_um
    shape_sigma_um = 0.0
    if spread > 0:
        wider = _fit_mu(z_um, s, gamma_um + spread, b)
        narrower = _fit_mu(z_um, s, max(gamma_um - spread, 1e-3), b)
        shape_sigma_um = abs(wider - narrower) / 2.0
    sigma_um = math.hypot(misfit_sigma_um, shape_sigma_um, floor_sigma_um)
    if sigma_um > high - low:  # located nowhere in particular: no measurement
        return free
    return PeakFit(mu_um, sigma_um, frozenset(), chosen_probability=1.0)
