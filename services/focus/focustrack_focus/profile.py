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
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.unprofiled import settings_without_entry

PROFILE_VERSION = 1
#: The noise floor (share of a curve's maximum) that turns an unusable metric off: with
#: noise as large as the maximum, no non-negative curve rises the `min_snr` (10) noise
#: sigmas a peak needs, so every result is `flat`. `serve focus --min-relative-noise 1`.
UNUSABLE_RELATIVE_NOISE = 1.0


class ProfileError(ValueError):
    """A profile file that cannot be read (the message says why)."""


@dataclass(frozen=True)
class MetricProfile:
    """One metric's constants on the microscope.

    relative_noise: its score noise, share of a curve's maximum (`PeakSettings`).
    systematic_sigma_um: its offset from the plane a person picks, a std, um.
    unusable_because: why it cannot serve on this microscope ("" when it can): then
        every curve it scores reads flat.
    curve_fwhm_um: the median full width at half maximum of its curves' peaks, um.
    coarse_step_um: the largest coarse-search step that keeps a frame above half the
        narrowest peaks (the estimator's lean search; `lean.COARSE_STEP_UM`), um.
    cross_validation: the folds' figures, for the reader.
    """

    relative_noise: float
    systematic_sigma_um: float
    unusable_because: str = ""
    curve_fwhm_um: float | None = None
    coarse_step_um: float | None = None
    cross_validation: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.relative_noise) and 0.0 <= self.relative_noise <= 1.0):
            raise ValueError(f"relative_noise must be in [0, 1], got {self.relative_noise}")
        if not (math.isfinite(self.systematic_sigma_um) and self.systematic_sigma_um >= 0.0):
            raise ValueError(f"systematic_sigma_um must be >= 0, got {self.systematic_sigma_um}")

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
        """The profile in `path`; ProfileError when it is missing or not a profile."""
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except OSError as error:
            raise ProfileError(f"cannot read the profile {path}: {error.strerror}") from None
        except json.JSONDecodeError as error:
            raise ProfileError(f"the profile {path} is not JSON: {error.msg}") from None
        return cls.from_json(data)
