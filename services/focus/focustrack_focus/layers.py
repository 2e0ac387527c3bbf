"""Two layers under one top: a peak broader than the slide's own, and the doubt it leaves.

A fold lays the section over itself a few um higher. Where the two layers lie closer than
the focus curve is wide, their peaks merge into one broad top, and its vertex lies between
the layers, in focus for neither (on the virtual slides' folds, 0.5 to 2 um from the
section, with the sigma of a clean peak). Nothing else about the curve says so: no second
peak, no edge. Its width does: a tile's top is as wide as the slide's curve (the optics
and the metric set it), and two layers widen and flatten it. Two Gaussian tops of width w
at +/- a from their middle give log(score) the curvature (a**2 - w**2) / w**4 there: a top
of width W with W**2 - w**2 = w**2 a**2 / (w**2 - a**2), at least a**2. So sqrt(W**2 - w**2)
is at least each layer's distance from the vertex (more as the top flattens): the std this
adds to the measurement, the honest side of the doubt.

The top's width is a log-parabola's over the three frames about the chosen peak (the
width of a Gaussian through them). The slide's own is the median over the clean tops read
so far (no flag: one peak inside the stack), learnt as a scan goes (`learn_top`, kept with
the slide's curve, `CurveModel.top_widths_um`). A top wider than `BROAD_TOP_RATIO` times
it is read as two layers (`layers_sigma_um`). The ratio was chosen on virtual slides of
seeds 1 and 2 (kf-2d's stacks of 5 frames 0.5 um apart): tiles without a fold 1.4 to 1.7
times the slide's median width, fold tiles whose vertex lay 0.8 to 2 um from the section
2.5 to 5.7 times.

A fold is a band across tiles, and a short stack's width is noisy (3 frames 0.5 um apart:
a top read 0.5 to 1.7 times the slide's on tiles of one layer), so a fold tile whose top
happens to read under twice the slide's is measured between its layers with the sigma of a
clean peak: a confident miss. So a tile beside one whose top was read as two layers
(the slide's `CurveModel.layered_tiles`, the eight around it and itself) is read as two
layers from `BESIDE_LAYERS_RATIO` times the slide's width on: the doubt a fold's band
leaves its neighbours, which costs no frame on tiles away from a fold. The ratio was chosen
on seeds 1 and 2 (kf-2d-lean's 3- and 5-frame stacks): the fold tiles read right there
(within 0.3 um of a layer) at 1.1 to 1.5 times, other tiles 0.5 to 1.65 times.
Heights and widths in um.
"""

from __future__ import annotations

import math

import numpy as np

from focustrack_core.domain import FocusFlag

#: A top this many times wider than the slide's is two layers ...
BROAD_TOP_RATIO = 2.0
#: ... or this many times, on a tile beside one read as two layers (a fold's band).
BESIDE_LAYERS_RATIO = 1.5
#: Clean tops a slide needs before its width is trusted, and the most it remembers.
MIN_TOPS = 5
MAX_TOPS = 50


def top_width_um(z_um: np.ndarray, scores: np.ndarray, peak_z_um: float) -> float | None:
    """The width (std of a Gaussian, um) of the top at `peak_z_um`: a log-parabola through
    the three frames about it (z (n,) ascending, at least 3, scores (n,); the frames of a
    short stack whose peak the slide's curve located between two of them, `curve_model`);
    None where that is no peak (scores not positive, no downward curvature)."""
    best = min(max(int(np.argmin(np.abs(z_um - peak_z_um))), 1), z_um.size - 2)
    window = slice(best - 1, best + 2)
    values = scores[window]
    if not np.all(values > 0):
        return None
    curvature = np.polyfit(z_um[window] - z_um[best], np.log(values), 2)[0]
    return math.sqrt(-1.0 / (2.0 * curvature)) if curvature < 0 else None


def layers_sigma_um(
    widths_um: list[float],
    z_um: np.ndarray,
    scores: np.ndarray,
    peak_z_um: float,
    *,
    beside_layers: bool = False,
) -> float:
    """The std (um) two layers under the top at `peak_z_um` add (0 where the top is no wider
    than `BROAD_TOP_RATIO` times the slide's, `BESIDE_LAYERS_RATIO` times on a tile
    `beside_layers`, or the slide has too few tops yet)."""
    if len(widths_um) < MIN_TOPS:
        return 0.0
    width_um = top_width_um(z_um, scores, peak_z_um)
    typical_um = float(np.median(widths_um))
    ratio = BESIDE_LAYERS_RATIO if beside_layers else BROAD_TOP_RATIO
    if width_um is None or width_um <= ratio * typical_um:
        return 0.0
    return math.sqrt(width_um**2 - typical_um**2)


def learn_top(
    widths_um: list[float],
    z_um: np.ndarray,
    scores: np.ndarray,
    best_z_um: float | None,
    flags: frozenset[FocusFlag],
    *,
    beside_layers: bool = False,
) -> bool:
    """Add the width of a clean top (a single peak inside its stack, no flag) to `widths_um`,
    unless it is read as two layers (`layers_sigma_um`, `beside_layers` as there); keep the
    last MAX_TOPS. True where the top was read as two layers (flagged or not)."""
    if best_z_um is None or z_um.size < 3:  # a pair has no top of its own
        return False
    width_um = top_width_um(z_um, scores, best_z_um)
    layers = layers_sigma_um(widths_um, z_um, scores, best_z_um, beside_layers=beside_layers) > 0
    if not (flags or width_um is None or layers):
        widths_um.append(width_um)
        del widths_um[:-MAX_TOPS]
    return layers
