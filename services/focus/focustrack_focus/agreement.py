"""Whether several focus metrics computed on the same frames agree on a peak.

A stack that one metric reads as flat (its curve's range a small share of its level or
within its own noise, `peak.find_peak`) may still hold a plane a person sees in focus: a
pale specimen under a low-magnification objective changes a low-frequency contrast
(normalised variance) by a fraction of a percent while its edges sharpen. Metrics that weigh
different spatial frequencies (`metrics.METRICS`) then peak on the same frame.

What they do not share is noise: a frame's noise moves each metric its own way. A camera
whose brightness alone wanders with z (Micro-Manager's demo camera, a lamp warming up)
leaves every contrast metric flat but for its noise, so their maxima fall where that
noise puts them; where the light dims, the relative photon noise grows and every
noise-sensitive metric rises with it, all on the same frame, but the noise-robust one
(Vollath's F4: white noise cancels in it, `NOISE_ROBUST_METRIC`) does not.

The rule (`agreed_peak`), over the metrics of every frame's centre (`agreement_scores`):
most metrics (more than half, `AGREE_MIN_METRICS` at least) have their maximum on an
interior frame within `AGREE_FRAMES` of the median of such maxima, each rising above both
of its curve's end frames (by `AGREE_RISE_SNR` of the curve's own noise where the curve is
long enough to measure it: `noise_bound.score_noise`), and the noise-robust metric's
maximum is among them. The median frame is then the agreed peak.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from focustrack_focus.metrics import METRICS
from focustrack_focus.noise_bound import score_noise

#: The metrics are compared on the centre of each frame, this many pixels square at most:
#: 0.6 ms for all six on one core, against 8 ms for one metric on a 2048 px frame.
AGREEMENT_CROP_PX = 128
#: The least number of metrics that must agree, and more than half of those computed (the
#: metrics weigh spatial frequencies differently; two could share a bias, and a coarse one,
#: the JPEG size, may see nothing in a very pale stack).
AGREE_MIN_METRICS = 3
#: Agreeing maxima lie within this many frames of the median of the interior ones ...
AGREE_FRAMES = 1
#: ... each rising this many of its curve's noise spreads above both end frames.
AGREE_RISE_SNR = 5.0
#: A metric that white noise leaves unchanged: where it is among the curves, it must agree.
NOISE_ROBUST_METRIC = "vollath_f4"


def agreement_scores(image: np.ndarray) -> np.ndarray:
    """Every metric of `metrics.METRICS` (in its order) on the centre of a preprocessed
    frame (h, w) float32, at most AGREEMENT_CROP_PX square: (len(METRICS),)."""
    h, w = image.shape
    y0, x0 = max((h - AGREEMENT_CROP_PX) // 2, 0), max((w - AGREEMENT_CROP_PX) // 2, 0)
    centre = np.ascontiguousarray(image[y0 : y0 + AGREEMENT_CROP_PX, x0 : x0 + AGREEMENT_CROP_PX])
    return np.array([metric(centre) for metric in METRICS.values()])


def agreed_peak(curves: Mapping[str, np.ndarray]) -> int | None:
    """The frame (index) on which the metrics' `curves` agree, or None (module docstring).

    curves: metric name -> scores (n,) over the same frames (`agreement_scores` of each
    frame); ValueError where their lengths differ."""
    lengths = {np.asarray(c).shape for c in curves.values()}
    if len(lengths) > 1:
        raise ValueError(f"curves over the same frames needed, got shapes {sorted(lengths)}")
    tops = []
    for values in curves.values():
        s = np.asarray(values, dtype=np.float64)
        top = int(np.argmax(s))
        noise, clean = score_noise(s)
        # a short curve's noise estimate takes in its peak's shape: then only the agreement
        rise = float(s[top] - max(s[0], s[-1]))
        if top not in (0, s.size - 1) and rise > (AGREE_RISE_SNR * noise if clean else 0.0):
            tops.append(top)
    if not tops:
        return None
    median = int(np.median(tops))
    agreeing = sum(abs(top - median) <= AGREE_FRAMES for top in tops)
    if agreeing < max(AGREE_MIN_METRICS, len(curves) // 2 + 1):
        return None
    robust = curves.get(NOISE_ROBUST_METRIC)
    if robust is not None and abs(int(np.argmax(robust)) - median) > AGREE_FRAMES:
        return None  # a peak the noise-robust metric does not see is the noise's
    return median
