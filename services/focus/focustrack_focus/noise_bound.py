"""A curve's own noise estimate, and how far it may fall short of its noise: an upper bound.

`score_noise` estimates a curve's score noise as the median absolute third difference
away from the top (a third difference vanishes on any locally quadratic curve). On a full
curve that median rests on dozens of differences; on a scanner's window of 7-11 frames, on
2-5, which overlap (the third differences of white noise are correlated: -0.75 at lag one),
and one window in twenty finds a noise 2.7-4.4 times smaller than the truth. A window of
a metric that barely sees the specimen (a faint bump a few noise spreads high) then reads a
"clean", quiet curve: its vertex gets a small sigma, and frames far from it, as high as its
top within the true noise, no chance of being the top.

Where the metric's noise on the microscope is not on record (a metric the service has no
entry for: `unprofiled`), the noise that sigma and the top's chances take
(`peak.find_peak`) is the estimate's upper confidence bound: the estimate over the quantile
of (estimate / true noise) at one minus the confidence, from white noise through the same
frames and the same differences left out (`bound_factor`: Monte Carlo with a fixed seed,
once per shape). It needs no constant of a microscope: a window's own count of differences.
The flat test and the choice of candidates keep the estimate itself: a bound there calls
clear peaks flat (docs/focus.md).
"""

from __future__ import annotations

import functools
import math

import numpy as np

#: Std of a normal distribution per unit of its median absolute deviation.
MAD_TO_SIGMA = 1.4826
#: Normal deviates drawn for each factor (a budget: more draws for a shorter curve, whose
#: estimate spreads most); the factor of a 5-11 frame window is then good to about 1 %.
_DEVIATES = 1_000_000


def away_from_top(n_frames: int, best: int) -> np.ndarray:
    """Which third differences (n_frames - 3,) of a curve whose highest frame is `best` keep
    clear of the top: difference i spans frames i .. i + 3, and those touching the top or
    its neighbours are left out (`score_noise`)."""
    first = np.arange(max(n_frames - 3, 0))
    return (first + 3 < best - 1) | (first > best + 1)


def noise_from_differences(d3: np.ndarray) -> np.ndarray:
    """The noise std that third differences (..., k) of white noise say: the MAD of each row
    over its normal share, over sqrt(20) (a third difference's variance is 20 sigma**2)."""
    return MAD_TO_SIGMA * np.median(np.abs(d3), axis=-1) / math.sqrt(20.0)


def score_noise(scores: np.ndarray) -> tuple[float, bool]:
    """Robust std of the score noise of a curve (n,), from its third differences.

    A third difference -s[i] + 3 s[i+1] - 3 s[i+2] + s[i+3] of white noise has
    variance 20 sigma**2, and it vanishes on any locally quadratic curve, so a
    smooth focus curve leaves it near zero except around a sharp peak. So the
    differences that touch the highest frame or its neighbours are left out,
    and the median of the rest ignores the few that the peak's shoulders still
    touch. Returns (sigma, clean): clean is False when fewer than two
    differences were away from the peak and all were used (an overestimate,
    fine for sigma, not for deciding that a curve is flat); (0.0, False) for
    fewer than 4 frames.
    """
    if scores.size < 4:
        return 0.0, False
    d3 = np.diff(scores, 3)
    away = away_from_top(scores.size, int(np.argmax(scores)))
    clean = np.count_nonzero(away) >= 2
    if clean:
        d3 = d3[away]
    return float(noise_from_differences(d3)), bool(clean)


def used_differences(n_frames: int, best: int) -> tuple[int, ...]:
    """The runs of consecutive third differences `score_noise` takes (sorted lengths):
    those away from the top where at least two are (a clean estimate), else all."""
    away = away_from_top(n_frames, best)
    if np.count_nonzero(away) < 2:
        return (away.size,)
    left = int(np.count_nonzero(away[: max(best, 0)]))
    return tuple(sorted(n for n in (left, int(np.count_nonzero(away)) - left) if n > 0))


@functools.lru_cache(maxsize=256)
def _factor(runs: tuple[int, ...], confidence: float) -> float:
    rng = np.random.default_rng(20261126)
    draws = _DEVIATES // sum(n + 3 for n in runs)
    # runs far apart share no frame: each run's differences from noise of its own
    d3 = np.concatenate([np.diff(rng.standard_normal((draws, n + 3)), 3) for n in runs], axis=1)
    return float(1.0 / np.quantile(noise_from_differences(d3), 1.0 - confidence))


def bound_factor(n_frames: int, best: int, confidence: float) -> float:
    """By how much to multiply `score_noise`'s estimate on a curve of `n_frames` frames
    whose highest is `best` for its upper bound at `confidence` (module docstring); 1 at
    confidence 0 (the estimate itself) or where there are fewer than 4 frames (no estimate)."""
    if not 0.0 <= confidence < 1.0:
        raise ValueError(f"a confidence in [0, 1), got {confidence}")
    if confidence == 0.0 or n_frames < 4:
        return 1.0
    return _factor(used_differences(n_frames, best), confidence)
