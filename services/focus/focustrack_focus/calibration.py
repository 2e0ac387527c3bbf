"""A focus metric's constants on a microscope, learnt from through-focus curves a person
labelled, and the figures that judge them.

Every curve goes through `focus_from_curve`, the path of POST /v1/focus/curve, read
as a predictive scanner acquires it (`windows`):

- full curves: all positions;
- windows: n samples (5, 7, 9, 11) spaced k steps (1, 2, 3), centred at every offset
  from the label up to one window length either way (so the label lies inside or up
  to half a window outside), clipped to the curve's positions.

Per metric (`summarise`): share within 1 and 2 steps of the label, the 2-sigma
coverage (|error| <= 2 sigma + half a step, the label's rounding), median sigma, flag
rates, and for windows whose label lies outside: the share whose edge flag points
toward it (right) and away (wrong). "Silent misses": results more than 3 steps off
with no warning flag and outside 2 sigma.

Honest calibration: the peak model's constants were chosen on the fit fields (1, 3,
..., 19 of the WSI curves, `real_data`); the held-out fields (2, 4, ..., 20) give the
headline figures. So are a measure's constants on the microscope (`Calibration`),
learnt afresh from the fit fields alone (`calibrate`) and then used on all: its score
noise (`PeakSettings.min_relative_noise`) and its systematic sigma
(`PeakSettings.systematic_sigma_um`: how far its own peak strays from the plane a
person picks).

A measure may also be unusable on the microscope, decided on the fit fields alone
(`usability`): when, read with its learnt noise, most of their windows are flat (it sees
too little of the specimen to serve a scanner), or when no systematic sigma up to the
median-sigma target reaches the coverage there (its own peak strays too far from focus
for any sigma that could meet that target). Such a measure is then given a noise floor
as large as the curve's maximum, so that every result it gives is `flat`: a warning
that names no z, never a silent miss.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from focustrack_core.domain import FocusFlag
from focustrack_focus.labelled_curves import LabelledCurve, wsi_curves
from focustrack_focus.noise_bound import score_noise
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings, focus_from_curve
from focustrack_focus.profile import UNUSABLE_RELATIVE_NOISE, MetricProfile
from focustrack_focus.real_data import WSI_STEP_UM, load_wsi_fields

#: (samples, spacing in steps) of the windows.
WINDOW_SHAPES = tuple((n, k) for n in (5, 7, 9, 11) for k in (1, 2, 3))
FIT_FIELDS = tuple(range(1, 21, 2))  # the constants were chosen on these
REPORT_FIELDS = tuple(range(2, 21, 2))  # the headline figures
#: The 2-sigma coverage the systematic sigma is learnt to reach on the fit fields (that of
#: a normal distribution), on full curves and on windows alike.
CALIBRATION_COVERAGE = 0.95
#: The grid (steps) on which the systematic sigma is learnt.
SYSTEMATIC_GRID_STEPS = 0.05
#: The target for the median sigma on 11x3 windows (steps; `focustrack bench focus --real`
#: holds a measure to it). A systematic sigma above it puts every interior sigma above it,
#: so it is also the largest systematic sigma a usable measure may need (`usability`).
MEDIAN_SIGMA_TARGET_STEPS = 0.75
#: A measure whose fit-field windows come back flat more often than this (most of them),
#: read with its learnt noise, is unusable on the microscope (`usability`).
MAX_FLAT_SHARE = 0.5
#: Flags that warn the caller the z is not an ordinary measurement.
WARNING_FLAGS = frozenset(
    {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH, FocusFlag.MULTI_PEAK, FocusFlag.AMBIGUOUS}
)


@dataclass(frozen=True)
class Window:
    """Positions (indices into the curve) of one acquisition and its shape ("full" or n x k)."""

    kind: str
    indices: np.ndarray


def windows(n_positions: int, label_index: int) -> Iterator[Window]:
    """The full curve, then every window of WINDOW_SHAPES centred up to a window length
    from the label (module docstring), within the curve's positions."""
    yield Window("full", np.arange(n_positions))
    for n, k in WINDOW_SHAPES:
        length = (n - 1) * k
        for centre in range(label_index - length, label_index + length + 1):
            first = centre - length // 2
            if first >= 0 and first + length < n_positions:
                yield Window(f"{n}x{k}", first + k * np.arange(n))


@dataclass(frozen=True)
class Reading:
    """One curve read: errors and sigma in steps (None where no z / no sigma), flags, and
    where the label lay: -1 below the window, 0 inside, +1 above."""

    field: int
    kind: str
    error_steps: float | None
    sigma_steps: float | None
    flags: frozenset[FocusFlag]
    label_side: int


def read_field(field: LabelledCurve, metric: str, settings: FocusSettings) -> list[Reading]:
    """Every window of one field's curve of `metric`, read as POST /v1/focus/curve would;
    errors and sigma in the curve's steps."""
    scores, z_um, step_um = field.scores[metric], field.z_um, field.step_um
    label_index = field.label_index
    out = []
    for window in windows(scores.size, label_index):
        result = focus_from_curve(z_um[window.indices], scores[window.indices], settings)
        lo, hi = window.indices[0], window.indices[-1]
        side = -1 if label_index < lo else 1 if label_index > hi else 0
        error = (
            None if result.best_z_um is None else (result.best_z_um - field.focus_z_um) / step_um
        )
        sigma = None if result.sigma_um is None else result.sigma_um / step_um
        out.append(Reading(field.number, window.kind, error, sigma, result.flags, side))
    return out


def summarise(readings: Sequence[Reading]) -> dict[str, float]:
    """The targets' figures over a set of readings (fractions; sigma in steps)."""
    inside = [r for r in readings if r.label_side == 0]
    measured = [r for r in inside if r.error_steps is not None and r.sigma_steps is not None]
    errors = np.array([abs(r.error_steps or 0.0) for r in measured])
    sigmas = np.array([r.sigma_steps or 0.0 for r in measured])
    covered = errors <= 2.0 * sigmas + 0.5
    outside = [r for r in readings if r.label_side != 0]

    def points(r: Reading, toward: bool) -> bool:
        flag = FocusFlag.EDGE_HIGH if (r.label_side > 0) == toward else FocusFlag.EDGE_LOW
        return flag in r.flags

    def silent(r: Reading) -> bool:
        if r.error_steps is None or r.flags & WARNING_FLAGS:
            return False
        if abs(r.error_steps) <= 3.0:
            return False
        return r.sigma_steps is None or abs(r.error_steps) > 2.0 * r.sigma_steps + 0.5

    def share(values: Sequence[bool] | np.ndarray) -> float:
        return float(np.mean(values)) if len(values) else math.nan

    def flag_rate(flag: FocusFlag) -> float:
        return share([flag in r.flags for r in inside])

    edge = {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH}
    return {
        "n_inside": float(len(inside)),
        "n_outside": float(len(outside)),
        "measured": share([r in measured for r in inside]) if inside else math.nan,
        "within_1_step": share(errors <= 1.0),
        "within_2_steps": share(errors <= 2.0),
        "coverage_2sigma": share(covered),
        "median_sigma_steps": float(np.median(sigmas)) if sigmas.size else math.nan,
        "multi_peak": flag_rate(FocusFlag.MULTI_PEAK),
        "ambiguous": flag_rate(FocusFlag.AMBIGUOUS),
        "flat": flag_rate(FocusFlag.FLAT),
        "edge_when_inside": share([bool(r.flags & edge) for r in inside]),
        "edge_right": share([points(r, True) for r in outside]),
        "edge_wrong": share([points(r, False) for r in outside]),
        "silent_miss": share([silent(r) for r in readings]),
    }


@dataclass(frozen=True)
class Calibration:
    """A measure's constants on this microscope (`PeakSettings`), learnt on the fit fields:
    its score noise as a share of a curve's maximum, its systematic sigma (steps of
    `step_um`; None where none up to `MEDIAN_SIGMA_TARGET_STEPS` reaches the coverage), and
    why it is unusable there ("" when it is usable)."""

    relative_noise: float = 0.0
    systematic_sigma_steps: float | None = 0.0
    unusable_because: str = ""
    step_um: float = WSI_STEP_UM
    #: the median width at half maximum of the fields' peaks, um (`curve_widths_um`);
    #: the peak model reads tops at a window's end against it
    curve_fwhm_um: float | None = None

    @property
    def usable(self) -> bool:
        return not self.unusable_because

    def entry(self, **record: Any) -> MetricProfile:
        """The measure's entry in a microscope profile (`record`: its other fields)."""
        return MetricProfile(
            self.relative_noise,
            self.step_um * (self.systematic_sigma_steps or 0.0),
            self.unusable_because,
            curve_fwhm_um=self.curve_fwhm_um,
            **record,
        )

    def settings(self) -> FocusSettings:
        """The service's settings for the measure: an unusable one reads every curve flat."""
        return FocusSettings(peak=self.entry().peak_settings(PeakSettings()))


def read_fields(
    fields: Sequence[LabelledCurve], metric: str, settings: FocusSettings
) -> list[Reading]:
    """`read_field` over every field."""
    return [r for field in fields for r in read_field(field, metric, settings)]


def real_curves(
    folder: Path,
    metrics: Iterable[str],
    numbers: Sequence[int] | None = None,
    calibration: dict[str, Calibration] | None = None,
) -> dict[str, list[Reading]]:
    """Every metric's readings over every field (or those `numbers`) and window of the WSI
    curves in `folder`, each metric read with its calibration (none where not given).
    `metrics` are taken one by one as they are read (a progress bar may wrap them)."""
    fields = wsi_curves(
        [f for f in load_wsi_fields(folder) if numbers is None or f.number in numbers]
    )
    calibration = calibration or {}
    return {
        metric: read_fields(fields, metric, calibration.get(metric, Calibration()).settings())
        for metric in metrics
    }


def scored_fields(
    fields: Sequence[LabelledCurve], metric: str
) -> tuple[list[LabelledCurve], list[int]]:
    """The fields whose curve of `metric` rises above 0, and the numbers of the others (every
    score 0 or below): a metric that sees nothing in a field cannot be calibrated there, its
    noise being a share of the curve's maximum (`learn_relative_noise`)."""
    kept = [f for f in fields if f.scores[metric].max() > 0.0]
    return kept, [f.number for f in fields if f.scores[metric].max() <= 0.0]


def learn_relative_noise(fields: Sequence[LabelledCurve], metric: str) -> float:
    """The metric's score noise as a share of a curve's maximum: the median over these
    fields' full curves (long enough for a clean estimate: `score_noise`), 2 digits; at
    most `UNUSABLE_RELATIVE_NOISE` (noise above the maximum turns the metric off all the
    same). Pass fields whose curves rise above 0 (`scored_fields`)."""
    shares = [score_noise(f.scores[metric])[0] / abs(f.scores[metric].max()) for f in fields]
    return min(UNUSABLE_RELATIVE_NOISE, float(f"{np.median(shares):.2g}"))


def label_free(fields: Sequence[LabelledCurve], metric: str) -> Calibration:
    """What the fields' curves say of the metric before its systematic sigma: its noise,
    the curves' step and their peaks' median width (3 digits)."""
    widths = curve_widths_um(fields, metric)
    return Calibration(
        learn_relative_noise(fields, metric),
        step_um=float(np.median([f.step_um for f in fields])),
        curve_fwhm_um=round(float(np.median(widths)), 3) if widths else None,
    )


def curve_widths_um(fields: Sequence[LabelledCurve], metric: str) -> list[float]:
    """The widths at half maximum (um) of the fields' peaks, where measured (`curve_fwhm_um`)."""
    return [w for f in fields if (w := curve_fwhm_um(f, metric)) is not None]


def coverage_with(readings: Sequence[Reading], systematic_steps: float) -> float:
    """The 2-sigma coverage (`summarise`) of readings made without a systematic sigma, had
    `systematic_steps` been added to their sigma in quadrature (as `find_peak` adds it)."""
    inside = [r for r in readings if r.label_side == 0 and r.sigma_steps is not None]
    if not inside:
        return math.nan
    errors = np.array([abs(r.error_steps or 0.0) for r in inside])
    sigmas = np.hypot([r.sigma_steps or 0.0 for r in inside], systematic_steps)
    return float(np.mean(errors <= 2.0 * sigmas + 0.5))


def learn_systematic_sigma(
    readings: Sequence[Reading], cap_steps: float = MEDIAN_SIGMA_TARGET_STEPS
) -> float | None:
    """The least systematic sigma (steps, on a grid of `SYSTEMATIC_GRID_STEPS`) with which
    full curves and windows each reach `CALIBRATION_COVERAGE` (readings made without one;
    pass only fit fields). 0 where they reach it already: a clear pick keeps its sigma.
    None where even `cap_steps` does not reach it. Parts with no measured reading (all
    flat) have nothing to cover and ask for nothing."""
    full = [r for r in readings if r.kind == "full"]
    parts = (full, [r for r in readings if r.kind != "full"])
    for step in range(round(cap_steps / SYSTEMATIC_GRID_STEPS) + 1):
        systematic = round(step * SYSTEMATIC_GRID_STEPS, 2)
        # NaN (nothing measured) is not below the coverage: such a part needs nothing
        if any(coverage_with(part, systematic) < CALIBRATION_COVERAGE for part in parts):
            continue
        if not field_offsets_covered(full, systematic) < CALIBRATION_COVERAGE:
            return systematic
    return None


def field_offsets_covered(full: Sequence[Reading], systematic_steps: float) -> float:
    """The share of fields whose full curve's offset from the label lies within 2
    `systematic_steps` and half a step (the label's rounding): the systematic sigma alone,
    without the full curve's own sigma. A metric's offset from the plane a person picks
    belongs to the field (its specimen), so every window of it carries the same offset,
    and a window, which sees less of the curve than the full one, may state a sigma far
    below it: the systematic sigma must cover the offset by itself. NaN without any."""
    offsets = np.array([abs(r.error_steps) for r in full if r.error_steps is not None])
    if offsets.size == 0:
        return math.nan
    return float(np.mean(offsets <= 2.0 * systematic_steps + 0.5))


def flat_share(readings: Sequence[Reading]) -> float:
    """The share of the windows (not full curves) among `readings` that came back flat."""
    flat = [FocusFlag.FLAT in r.flags for r in readings if r.kind != "full"]
    return float(np.mean(flat)) if flat else math.nan


def usability(readings: Sequence[Reading], systematic_steps: float | None) -> str:
    """Why a measure is unusable on the microscope, from its fit-field readings (made
    with its learnt noise, no systematic sigma) and the systematic sigma learnt from them;
    "" when it is usable. Either rule alone keeps it from meeting the targets: a flat
    window points nowhere (no edge flag, no z), and a systematic sigma above the median
    sigma target puts every sigma above it."""
    reasons = []
    flat = flat_share(readings)
    if flat > MAX_FLAT_SHARE:
        reasons.append(f"{flat:.0%} of the fit fields' windows flat (> {MAX_FLAT_SHARE:.0%})")
    if systematic_steps is None:
        reasons.append(
            f"no systematic sigma up to {MEDIAN_SIGMA_TARGET_STEPS} step reaches "
            f"{CALIBRATION_COVERAGE:.0%} coverage on the fit fields"
        )
    return "; ".join(reasons)


def learn_constants(noise: Calibration, readings: Sequence[Reading]) -> Calibration:
    """`noise` with the systematic sigma and the usability that `readings` (made with that
    noise, no systematic sigma, on labelled fields) ask for."""
    systematic = learn_systematic_sigma(readings)
    return replace(
        noise, systematic_sigma_steps=systematic, unusable_because=usability(readings, systematic)
    )


def calibrate_metric(
    fields: Sequence[LabelledCurve], metric: str
) -> tuple[Calibration, list[Reading]]:
    """One metric's calibration learnt on `fields` (all of one z step): its noise first,
    then the systematic sigma that the readings with that noise still need, then whether
    it is usable at all (`usability`); with those readings (no systematic sigma in them)."""
    noise = label_free(fields, metric)
    readings = read_fields(fields, metric, noise.settings())
    return learn_constants(noise, readings), readings


def calibrate(folder: Path, metrics: Iterable[str]) -> dict[str, Calibration]:
    """Every metric's calibration, learnt on the fit fields of the WSI curves in `folder`
    alone (`calibrate_metric`; an unusable one then reads every curve flat). `metrics` are
    taken one by one, as by `real_curves`."""
    fit_fields = wsi_curves([f for f in load_wsi_fields(folder) if f.number in FIT_FIELDS])
    return {metric: calibrate_metric(fit_fields, metric)[0] for metric in metrics}


def report(readings: dict[str, list[Reading]], fields: Sequence[int]) -> dict[str, dict]:
    """Per metric: figures on full curves, on all windows, and on 11x3 windows, over `fields`."""
    out: dict[str, dict] = {}
    for metric, rows in readings.items():
        out[metric] = parts([r for r in rows if r.field in fields])
    return out


def with_constants(readings: Sequence[Reading], constants: Calibration) -> list[Reading]:
    """Readings made with `constants`' noise and no systematic sigma, as they read with its
    systematic sigma too (added to sigma in quadrature, as `find_peak` adds it), or, where
    the measure is unusable, flat (as it reads every curve then)."""
    if not constants.usable:
        flat = frozenset({FocusFlag.FLAT})
        return [replace(r, error_steps=None, sigma_steps=None, flags=flat) for r in readings]
    systematic = constants.systematic_sigma_steps or 0.0
    return [
        r
        if r.sigma_steps is None
        else replace(r, sigma_steps=math.hypot(r.sigma_steps, systematic))
        for r in readings
    ]


@dataclass(frozen=True)
class Fold:
    """One fold of a cross-validation: the fields held out, the constants learnt on the
    others, and the held-out fields' figures with them (`parts`)."""

    held_out: tuple[int, ...]
    constants: Calibration
    figures: dict[str, dict[str, float]]
    readings: list[Reading]


def parts(readings: Sequence[Reading]) -> dict[str, dict[str, float]]:
    """The figures (`summarise`) on full curves, on all windows and on 11x3 windows."""
    return {
        "full": summarise([r for r in readings if r.kind == "full"]),
        "windows": summarise([r for r in readings if r.kind != "full"]),
        "windows_11x3": summarise([r for r in readings if r.kind == "11x3"]),
    }


def cross_validate(
    fields: Sequence[LabelledCurve], metric: str, n_folds: int
) -> tuple[Calibration, list[Fold]]:
    """A metric's constants learnt on every field, and `n_folds` folds (fields dealt in turn)
    each learning the label-dependent constants (systematic sigma, usability) on the other
    folds and reporting on its own fields. The noise is learnt once on every field: it
    needs no label (a user could measure it on the held-out curves themselves), so every
    field is read once with it and the folds only re-weigh those readings
    (`with_constants`)."""
    if not 2 <= n_folds <= len(fields):
        raise ValueError(f"{n_folds} folds over {len(fields)} fields: need 2 .. {len(fields)}")
    noise = label_free(fields, metric)
    readings = read_fields(fields, metric, noise.settings())
    folds = []
    for fold in range(n_folds):
        held_out = tuple(f.number for f in fields[fold::n_folds])
        learnt = learn_constants(noise, [r for r in readings if r.field not in held_out])
        tested = with_constants([r for r in readings if r.field in held_out], learnt)
        folds.append(Fold(held_out, learnt, parts(tested), tested))
    return learn_constants(noise, readings), folds


def curve_fwhm_um(field: LabelledCurve, metric: str) -> float | None:
    """The full width at half maximum (um) of the peak nearest the label on the field's full
    curve, above the curve's lowest score (the background); None where the peak does not
    fall to half on both sides within the curve. Linear interpolation between frames."""
    s, z = field.scores[metric], field.z_um
    near = np.abs(np.arange(s.size) - field.label_index) <= 2
    top = int(np.argmax(np.where(near, s, -np.inf)))
    half = s.min() + (s[top] - s.min()) / 2.0
    below = np.flatnonzero(s < half)
    left, right = below[below < top], below[below > top]
    if left.size == 0 or right.size == 0:
        return None
    i, j = left[-1], right[0]
    z_left = z[i] + (half - s[i]) / (s[i + 1] - s[i]) * (z[i + 1] - z[i])
    z_right = z[j - 1] + (s[j - 1] - half) / (s[j - 1] - s[j]) * (z[j] - z[j - 1])
    return float(z_right - z_left)
