"""A microscope profile: each focus metric's constants on one microscope, in a JSON file.

`focustrack focus calibrate` learns it from a user's labelled curves; `serve focus
--profile FILE` loads it, and a curve's (or stack's) `metric` names the entry that reads
it. A metric without an entry is read with the service's own settings if it is one of the
service's metrics, else as a metric the service knows nothing of (`unprofiled`).

The file: ``{"version": 1, "source": "...", "metrics": {"METRIC": {"relative_noise": r,
"systematic_sigma_um": s, "unusable_because": "", "curve_fwhm_um": w, "coarse_step_um": c,
"cross_validation": {...}}, ...}}``. ``cross_validation`` (the
folds' figures) is a record for the reader; the service reads only the constants.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from focustrack_core.domain import MAX_ABS_Z_UM
from focustrack_focus.peak import MAX_SYSTEMATIC_SIGMA_UM, PeakSettings, check_number
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.unprofiled import settings_without_entry

PROFILE_VERSION = 1
#: The noise floor (share of a curve's maximum) that turns an unusable metric off: with
#: noise as large as the maximum, no non-negative curve rises the `min_snr` (10) noise
#: sigmas a peak needs, so every result is `flat`. `serve focus --min-relative-noise 1`.
UNUSABLE_RELATIVE_NOISE = 1.0
#: Longest metric name, characters: a curve's `metric` label picks an entry, and the REST
#: app refuses a longer label (a name longer than this is an entry no curve could pick).
MAX_METRIC_NAME_CHARS = 64
#: Widest peak (`curve_fwhm_um`) or coarse step (`coarse_step_um`), um: the widest z range
#: of any curve (z within +/-`MAX_ABS_Z_UM`); a wider one is a unit gone wrong.
MAX_CURVE_WIDTH_UM = 2.0 * MAX_ABS_Z_UM


def metric_name_problem(name: str) -> str | None:
    """What is wrong with a metric's name in a profile or a file of labelled curves (None:
    nothing): a curve's label picks its entry, and no label is empty or over
    MAX_METRIC_NAME_CHARS characters (the REST app refuses those)."""
    if not name:
        return "a metric's name is not empty (a curve's label names it)"
    if len(name) > MAX_METRIC_NAME_CHARS:
        return (
            f"metric {name[:MAX_METRIC_NAME_CHARS]!r}...: a metric's name is at most "
            f"{MAX_METRIC_NAME_CHARS} characters (a curve's label names it)"
        )
    return None


class ProfileError(ValueError):
    """A profile file that cannot be read (the message says why)."""


@dataclass(frozen=True)
class MetricProfile:
    """One metric's constants on the microscope.

    relative_noise: its score noise, share of a curve's maximum (`PeakSettings`), 0 .. 1.
    systematic_sigma_um: its offset from the plane a person picks, a std, um, 0 ..
        `MAX_SYSTEMATIC_SIGMA_UM`.
    unusable_because: why it cannot serve on this microscope ("" when it can): then
        every curve it scores reads flat.
    curve_fwhm_um: the median full width at half maximum of its curves' peaks, um, above 0
        (None: not measured).
    coarse_step_um: the largest coarse-search step that keeps a frame above half the
        narrowest peaks (the estimator's lean search; `lean.COARSE_STEP_UM`), um, above 0
        (None: not measured).
    cross_validation: the folds' figures, for the reader.
    """

    relative_noise: float
    systematic_sigma_um: float
    unusable_because: str = ""
    curve_fwhm_um: float | None = None
    coarse_step_um: float | None = None
    cross_validation: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """ValueError naming the first field of the wrong type or out of its range: a file
        is read here, and a value the peak maths cannot take would fail every curve."""
        check_number("relative_noise", self.relative_noise, 0.0, 1.0, above=False)
        check_number(
            "systematic_sigma_um (um)",
            self.systematic_sigma_um,
            0.0,
            MAX_SYSTEMATIC_SIGMA_UM,
            above=False,
        )
        if not isinstance(self.unusable_because, str):
            raise ValueError(
                f'unusable_because must be a string ("" when usable), got {self.unusable_because!r}'
            )
        for name in ("curve_fwhm_um", "coarse_step_um"):
            if (width := getattr(self, name)) is not None:
                check_number(f"{name} (um, or null)", width, 0.0, MAX_CURVE_WIDTH_UM, above=True)
        if not isinstance(self.cross_validation, dict):
            raise ValueError(
                f"cross_validation must be an object, got {type(self.cross_validation).__name__}"
            )

    @property
    def usable(self) -> bool:
        return not self.unusable_because

    def peak_settings(self, base: PeakSettings) -> PeakSettings:
        """`base` with this metric's constants: an unusable one reads every curve flat."""
        if not self.usable:
            return replace(base, min_relative_noise=UNUSABLE_RELATIVE_NOISE)
        return replace(
            base,
            min_relative_noise=self.relative_noise,
            systematic_sigma_um=self.systematic_sigma_um,
            curve_fwhm_um=self.curve_fwhm_um,
        )


@dataclass(frozen=True)
class MicroscopeProfile:
    """Every calibrated metric's constants (`MetricProfile`), by the metric's name."""

    metrics: dict[str, MetricProfile]
    source: str = ""

    def settings_for(self, metric: str, base: FocusSettings) -> FocusSettings:
        """How a curve labelled `metric` is read: `base` with the metric's entry, or where
        the profile has none, `base` for one of the service's own metrics and the reading
        of a metric it knows nothing of for any other (`unprofiled`)."""
        entry = self.metrics.get(metric)
        if entry is None:
            return settings_without_entry(metric, base)
        return replace(base, peak=entry.peak_settings(base.peak))

    def to_json(self) -> dict[str, Any]:
        return {
            "version": PROFILE_VERSION,
            "source": self.source,
            "metrics": {name: asdict(entry) for name, entry in self.metrics.items()},
        }

    @classmethod
    def from_json(cls, data: Any) -> MicroscopeProfile:
        """The profile of a parsed file; ProfileError saying what is wrong."""
        if not isinstance(data, dict) or not isinstance(data.get("metrics"), dict):
            raise ProfileError('a profile is an object with "metrics": {"METRIC": {...}}')
        if data.get("version") != PROFILE_VERSION:
            raise ProfileError(f"profile version {data.get('version')!r}; this reads 1")
        metrics = {}
        for name, entry in data["metrics"].items():
            if problem := metric_name_problem(name):
                raise ProfileError(problem)
            if not isinstance(entry, dict):
                raise ProfileError(f"metric {name!r}: an entry is an object of its constants")
            try:
                metrics[name] = MetricProfile(**entry)
            except (TypeError, ValueError) as error:
                raise ProfileError(f"metric {name!r}: {error}") from None
        return cls(metrics, str(data.get("source", "")))

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> MicroscopeProfile:
        """The profile in `path`; ProfileError naming `path` when it is missing or not a
        profile."""
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except OSError as error:
            raise ProfileError(f"cannot read the profile {path}: {error.strerror}") from None
        except UnicodeDecodeError:  # a binary file (a PNG), or text in another encoding
            raise ProfileError(f"the profile {path} is not UTF-8 text (JSON)") from None
        except json.JSONDecodeError as error:
            raise ProfileError(f"the profile {path} is not JSON: {error.msg}") from None
        try:
            return cls.from_json(data)
        except ProfileError as error:
            raise ProfileError(f"the profile {path}: {error}") from None
