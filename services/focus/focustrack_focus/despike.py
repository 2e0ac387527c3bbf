"""One-frame outliers of a focus curve (spikes and dips), replaced by their neighbours'
prediction before the curve is read (`peak.find_peak`)."""

from __future__ import annotations

import functools
import math

import numpy as np

#: How `despike` predicts a frame from its neighbours (offsets in frames -> weights), and
#: the std of the prediction's residual on white noise of unit std.
_PREDICTORS: dict[str, tuple[dict[int, float], float]] = {
    # cubic interpolation from two frames each side
    "interior": ({-2: -1 / 6, -1: 4 / 6, 1: 4 / 6, 2: -1 / 6}, math.sqrt(1 + 34 / 36)),
    # second frame: quadratic interpolation from the end frame and the next two
    "second": ({-1: 1 / 3, 1: 1.0, 2: -1 / 3}, math.sqrt(1 + 1 / 9 + 1 + 1 / 9)),
    # end frame: linear extrapolation from the next two
    "end": ({1: 2.0, 2: -1.0}, math.sqrt(1 + 4 + 1)),
}


@functools.lru_cache(maxsize=64)
def _outlier_allowance(step_over_width: float, predictor: str) -> float:
    """The largest residual, as a share of the peak's height, that a Gaussian peak of std w
    sampled every `step_over_width` * w leaves against `predictor`, over every phase: the
    peak within 4 w of the frame or of any frame the predictor reads (farther from all of
    them it leaves none). (Within 4 w of the frame alone, as it was, a peak on a neighbour
    of frames far apart went unseen: the end frame below a one-frame peak, 5 um steps, was
    taken for an outlier and the curve read at that end. One range spanning them all took
    seconds for frames 1e5 sigmas apart.)"""
    weights, _ = _PREDICTORS[predictor]
    near_a_frame = np.linspace(-4.0, 4.0, 161)
    # the peak at frame k (offset k from the frame judged) is at phase -step_over_width * k
    phases = np.concatenate([near_a_frame - step_over_width * k for k in (0, *weights)])

    def gaussian(offset: int) -> np.ndarray:
        return np.exp(-0.5 * (phases + step_over_width * offset) ** 2)

    residual = gaussian(0) - sum(w * gaussian(k) for k, w in weights.items())
    return float(np.abs(residual).max())


#: How much more than the narrowest peak's largest residual a frame must depart to be an
#: outlier (`despike`): a frame departing just as much is that peak, sampled where its
#: neighbours are nearly zero. Without it a one-frame peak on a flat baseline, 4 or more
#: of the narrowest peak's sigmas from its neighbours, departed 1.00000000000002 times its
#: allowance (or 1.0005 at 4 sigmas, where the peak's neighbours hold 3e-4 of it), was
#: removed and the curve read as flat. (A real dip, WSI field 5's, departs 1.005 to 1.01
#: times its allowance: the slack stays below it.)
OUTLIER_SLACK = 1.001


def despike(z: np.ndarray, s: np.ndarray, noise: float, min_peak_sigma_um: float) -> np.ndarray:
    """The curve (n,) with one-frame outliers (spikes and dips) replaced by their prediction.

    A frame is an outlier when it departs from what its neighbours predict
    (`_PREDICTORS`: cubic interpolation from two frames each side; near an end,
    quadratic interpolation or linear extrapolation) by more than any real peak
    could make it: a peak is at least as wide as the optics' depth of field (a
    Gaussian of std `min_peak_sigma_um`), and the largest residual such a peak
    leaves is `_outlier_allowance` times its height, at most the curve's range;
    and by more than 4 noise sigmas. Where frames are as far apart as the depth of
    field, a one-frame peak is possible and nothing is removed. One frame is replaced at
    a time: of those beyond their allowance, the one whose replacement leaves the others'
    worst departure least (an outlier spoils its neighbours' predictions: a dip beside an
    end frame makes the end frame, extrapolated through it, look the worse one). Curves
    of fewer than 5 frames are returned as they are.
    """
    if s.size < 5:
        return s
    ratio = round(float(np.median(np.diff(z))) / min_peak_sigma_um, 3)
    span = float(s.max() - s.min())
    n = s.size
    kinds = ["end", "second"] + ["interior"] * (n - 4) + ["second", "end"]
    allowance = np.array(
        [
            max(_outlier_allowance(ratio, kind) * span, 4.0 * _PREDICTORS[kind][1] * noise)
            for kind in kinds
        ]
    )

    def departures(curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each frame's departure from its prediction over its allowance (n,), and the
        predictions (n,)."""
        predicted = np.empty(n)
        for i, kind in enumerate(kinds):
            mirror = -1 if i > n // 2 else 1  # near the high end, offsets point downwards
            weights = _PREDICTORS[kind][0]
            predicted[i] = sum(w * curve[i + mirror * k] for k, w in weights.items())
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(allowance > 0, np.abs(curve - predicted) / allowance, 0.0), predicted

    out = s.copy()
    for _ in range(n // 4):
        excess, predicted = departures(out)
        suspects = np.flatnonzero(excess > OUTLIER_SLACK)
        if suspects.size == 0:
            break
        trials = []
        for i in suspects:
            trial = out.copy()
            trial[i] = predicted[i]
            trials.append((float(np.delete(departures(trial)[0], i).max()), int(i)))
        worst = min(trials)[1]
        out[worst] = predicted[worst]
    return out
