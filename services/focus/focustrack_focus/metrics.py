"""Focus metrics: one number per preprocessed frame, largest in focus.

Every metric takes the (h, w) float32 image that `Preprocess` returns and
gives a float; `METRICS` names them (the names are the wire and REST names).
The operators follow Pertuz, Puig & Garcia 2013 ("Analysis of focus measure
operators for shape-from-focus") and Sun, Duthaler & Nelson 2004; the JPEG
size is the thesis' best performer (Appendix A, Table A-1).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

FocusMetric = Callable[[np.ndarray], float]

_TINY = float(np.finfo(np.float32).tiny)


def normalised_variance(image: np.ndarray) -> float:
    """Grey-level variance over the mean, sum((I - mu)**2) / (N mu) (Groen et al. 1985).

    Dividing by the mean makes it insensitive to the illumination level and,
    for photon noise, puts the noise floor near a constant.
    """
    mean, std = cv2.meanStdDev(image)
    return float(std.item() ** 2 / max(mean.item(), _TINY))


def variance_of_laplacian(image: np.ndarray) -> float:
    """Variance of the 3x3 Laplacian (Pech-Pacheco et al. 2000)."""
    _, std = cv2.meanStdDev(cv2.Laplacian(image, cv2.CV_32F, ksize=1))
    return float(std.item() ** 2)


def tenengrad(image: np.ndarray) -> float:
    """Mean squared Sobel gradient magnitude, mean(Gx**2 + Gy**2) (Tenenbaum 1970)."""
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3)
    return float(cv2.mean(cv2.magnitude(gx, gy) ** 2)[0])


def brenner(image: np.ndarray) -> float:
    """Mean squared difference of pixels two apart, both directions (Brenner et al. 1976)."""
    dx = image[:, 2:] - image[:, :-2]
    dy = image[2:, :] - image[:-2, :]
    return float(cv2.mean(dx * dx)[0] + cv2.mean(dy * dy)[0])


def vollath_f4(image: np.ndarray) -> float:
    """Vollath's autocorrelation F4, mean(I(x) I(x+1) - I(x) I(x+2)), both directions.

    Noise-robust (white noise is uncorrelated at lags 1 and 2 alike, so it
    cancels), which is why Sun et al. 2004 rank it near the top for brightfield.
    Computed on I - mean(I): the same autocorrelation difference on an unbounded
    image, but on a finite one the mean would multiply the frame's edge terms
    (mean(I(x+1) - I(x+2)) telescopes to them), whose noise then swamps the peak.
    """
    centred = cv2.subtract(image, cv2.mean(image)[0])
    h = centred[:, :-2] * (centred[:, 1:-1] - centred[:, 2:])
    v = centred[:-2, :] * (centred[1:-1, :] - centred[2:, :])
    return float(cv2.mean(h)[0] + cv2.mean(v)[0])


def jpeg_size(image: np.ndarray, quality: int = 90) -> float:
    """Size in bytes of the frame JPEG-encoded at `quality` (thesis Table A-1, best: 0.97 um).

    The frame is scaled so that its mean is grey level 96 (brightness does not
    move the size; contrast does), then clipped to 8 bits.
    """
    scale = 96.0 / max(float(cv2.mean(image)[0]), _TINY)
    grey = cv2.convertScaleAbs(image, alpha=scale)
    ok, encoded = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"JPEG encoding failed for a frame of shape {image.shape}")
    return float(encoded.size)


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
