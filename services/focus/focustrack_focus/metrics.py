"""Focus metrics: one number per preprocessed frame, largest in focus.

Every metric takes the (h, w) float32 image that `Preprocess` returns and
gives a float; `METRICS` names them (the names are the wire and REST names).
The operators follow Pertuz, Puig & Garcia 2013 ("Analysis of focus measure
operators for shape-from-focus") and Sun, Duthaler & Nelson 2004; the JPEG
size is the thesis' best performer (Appendix A, Table A-1).

Every metric is a contrast: it is unchanged when the frame is multiplied by a
constant (each divides by the power of the mean that its operator scales with).
Focus moves contrast, not brightness; a stack whose brightness alone changes
with z (a lamp's drift, an exposure ramp, Micro-Manager's demo camera, whose
waves dim away from z = 0 but never blur) then gives a flat curve, not a peak.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from focustrack_focus import filters

FocusMetric = Callable[[np.ndarray], float]

_TINY = float(np.finfo(np.float32).tiny)

#: 3x3 Laplacian (OpenCV's `Laplacian` with ksize=1) and Sobel x derivative.
_LAPLACIAN = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], dtype=np.float32)
_SOBEL_X = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], dtype=np.float32)


def _mean(image: np.ndarray) -> float:
    """The frame's mean, floored at the smallest float32 (a black frame divides by it)."""
    return max(filters.BACKEND.mean(image), _TINY)


def normalised_variance(image: np.ndarray) -> float:
    """Squared coefficient of variation, var(I) / mu**2.

    Groen et al. 1985's normalised variance, var(I) / mu, divided once more by
    the mean so that it is a contrast (module docstring); for photon noise its
    floor within a stack (one brightness) is still a constant.
    """
    mean, std = filters.BACKEND.mean_std(image)
    return std**2 / max(mean, _TINY) ** 2


def variance_of_laplacian(image: np.ndarray) -> float:
    """Variance of the 3x3 Laplacian over mu**2 (Pech-Pacheco et al. 2000)."""
    backend = filters.BACKEND
    _, std = backend.mean_std(backend.correlate(image, _LAPLACIAN))
    return std**2 / _mean(image) ** 2


def tenengrad(image: np.ndarray) -> float:
    """Mean squared Sobel gradient magnitude over mu**2, mean(Gx**2 + Gy**2) (Tenenbaum 1970)."""
    backend = filters.BACKEND
    gx = backend.correlate(image, _SOBEL_X)
    gy = backend.correlate(image, _SOBEL_X.T)
    return backend.mean(gx * gx + gy * gy) / _mean(image) ** 2


def brenner(image: np.ndarray) -> float:
    """Mean squared difference of pixels two apart, both directions, over mu**2
    (Brenner et al. 1976)."""
    mean = filters.BACKEND.mean
    dx = image[:, 2:] - image[:, :-2]
    dy = image[2:, :] - image[:-2, :]
    return (mean(dx * dx) + mean(dy * dy)) / _mean(image) ** 2


def vollath_f4(image: np.ndarray) -> float:
    """Vollath's autocorrelation F4, mean(I(x) I(x+1) - I(x) I(x+2)), both directions,
    over mu**2.

    Noise-robust (white noise is uncorrelated at lags 1 and 2 alike, so it
    cancels), which is why Sun et al. 2004 rank it near the top for brightfield.
    Computed on I - mean(I): the same autocorrelation difference on an unbounded
    image, but on a finite one the mean would multiply the frame's edge terms
    (mean(I(x+1) - I(x+2)) telescopes to them), whose noise then swamps the peak.
    """
    backend = filters.BACKEND
    brightness = _mean(image)
    centred = image - np.float32(brightness)
    h = centred[:, :-2] * (centred[:, 1:-1] - centred[:, 2:])
    v = centred[:-2, :] * (centred[1:-1, :] - centred[2:, :])
    return (backend.mean(h) + backend.mean(v)) / brightness**2


def jpeg_size(image: np.ndarray, quality: int = 90) -> float:
    """Size in bytes of the frame JPEG-encoded at `quality` (thesis Table A-1, best: 0.97 um).

    The frame is scaled so that its mean is grey level 96 (brightness does not
    move the size; contrast does), then clipped to 8 bits. Needs OpenCV.
    """
    return float(filters.BACKEND.jpeg_bytes(image, 96.0 / _mean(image), quality))


#: Metric name -> function. The first is the default.
METRICS: dict[str, FocusMetric] = {
    "normalised_variance": normalised_variance,
    "variance_of_laplacian": variance_of_laplacian,
    "tenengrad": tenengrad,
    "brenner": brenner,
    "vollath_f4": vollath_f4,
    "jpeg_size": jpeg_size,
}
DEFAULT_METRIC = "normalised_variance"


def get_metric(name: str) -> FocusMetric:
    """The metric called `name`; ValueError naming the known ones otherwise."""
    try:
        return METRICS[name]
    except KeyError:
        raise ValueError(f"unknown focus metric {name!r}; known: {', '.join(METRICS)}") from None
