"""A z-stack (or a curve of scores) in, a `FocusResult` out: one path for REST, Zenoh, bench."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from focustrack.services.estimator.strategy import FocusFlag, Measurement
from focustrack.services.focus.metrics import DEFAULT_METRIC, get_metric
from focustrack.services.focus.peak import PeakSettings, find_peak, validate_curve
from focustrack.services.focus.preprocess import Preprocess


@dataclass(frozen=True)
class FocusSettings:
    """Everything that decides how a stack is read: preprocessing, metric, peak reading."""

    preprocess: Preprocess = field(default_factory=Preprocess)
    metric: str = DEFAULT_METRIC
    peak: PeakSettings = field(default_factory=PeakSettings)

    def __post_init__(self) -> None:
        get_metric(self.metric)  # fail early on an unknown name


@dataclass(frozen=True)
class FocusResult:
    """The focus of one stack: its curve, best z and sigma (um, None where none), flags.

    z_um and scores have shape (n,), sorted by z. compute_time_s is the wall time
    of metric and fit in seconds.
    """

    z_um: np.ndarray
    scores: np.ndarray
    best_z_um: float | None
    sigma_um: float | None
    flags: frozenset[FocusFlag]
    metric: str
    compute_time_s: float

    def measurement(self) -> Measurement:
        """The result as the estimator's `Measurement` (no z for a flat curve)."""
        return Measurement(self.best_z_um, self.sigma_um, self.flags)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON types; flags sorted for a stable output."""
        return {
            "z_um": self.z_um.tolist(),
            "scores": self.scores.tolist(),
            "best_z_um": self.best_z_um,
            "sigma_um": self.sigma_um,
            "flags": sorted(str(flag) for flag in self.flags),
            "metric": self.metric,
            "compute_time_s": self.compute_time_s,
        }


def focus_scores(frames: np.ndarray, settings: FocusSettings) -> np.ndarray:
    """The metric of every frame of a stack (n, H, W) or (n, H, W, C) -> scores (n,)."""
    metric = get_metric(settings.metric)
    return np.array([metric(settings.preprocess(frame)) for frame in frames], dtype=np.float64)


def focus_from_curve(
    z_um: np.ndarray, scores: np.ndarray, settings: FocusSettings, *, started_s: float | None = None
) -> FocusResult:
    """Read a curve of scores (n,) at z_um (n,); `started_s` (perf_counter) times the whole job."""
    started_s = time.perf_counter() if started_s is None else started_s
    z, s = validate_curve(z_um, scores)
    fit = find_peak(z, s, settings.peak)
    return FocusResult(
        z_um=z,
        scores=s,
        best_z_um=fit.z_um,
        sigma_um=fit.sigma_um,
        flags=fit.flags,
        metric=settings.metric,
        compute_time_s=time.perf_counter() - started_s,
    )


def focus_stack(frames: np.ndarray, z_um: np.ndarray, settings: FocusSettings) -> FocusResult:
    """The focus of a z-stack: frames (n, H, W) or (n, H, W, C) taken at z_um (n,)."""
    started_s = time.perf_counter()
    if frames.ndim not in (3, 4):
        raise ValueError(f"a z-stack is (n, H, W) or (n, H, W, C), got shape {frames.shape}")
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 1 or z.size != frames.shape[0]:
        raise ValueError(f"{frames.shape[0]} frames but {z.size} z values: one z per frame needed")
    validate_curve(z, np.zeros_like(z))  # frame count and z values, before any pixel work
    if frames.dtype.kind not in "uif":
        raise ValueError(f"pixels must be integers or floats, got dtype {frames.dtype}")
    if frames.dtype.kind == "f" and not np.all(np.isfinite(frames)):
        raise ValueError("pixels must be finite (NaN or infinity found)")
    return focus_from_curve(z, focus_scores(frames, settings), settings, started_s=started_s)
