"""Through-focus curves a person labelled, in the JSONL form `focustrack focus calibrate` reads.

One line per field: ``{"z_um": [...], "scores": {"METRIC": [...], ...}, "focus_z_um": z}``
(z in um, one score per z for every metric; the label is the z a person picked as in
focus). An optional ``"field"`` (an integer) names the field; without it a field is
numbered by its line (1, 2, ...). Blank lines are skipped. A line that breaks the form
is refused with its line number and what is wrong (`CurvesFileError`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from focustrack_focus.peak import validate_curve
from focustrack_focus.profile import metric_name_problem
from focustrack_focus.real_data import WSI_STEP_UM, WsiField


class CurvesFileError(ValueError):
    """A curves file that breaks the JSONL form (the message names the line)."""


@dataclass(frozen=True)
class LabelledCurve:
    """One field: z (n,) in um, sorted, the scores (n,) of each metric, the focus a person
    picked (um) and the field's number."""

    number: int
    z_um: np.ndarray
    scores: dict[str, np.ndarray]
    focus_z_um: float

    @property
    def step_um(self) -> float:
        """The curve's z step, um (the median spacing)."""
        return float(np.median(np.diff(self.z_um)))

    @property
    def label_index(self) -> int:
        """The position nearest the labelled focus."""
        return int(np.argmin(np.abs(self.z_um - self.focus_z_um)))

    def to_json(self) -> dict:
        return {
            "field": self.number,
            "z_um": self.z_um.tolist(),
            "scores": {name: values.tolist() for name, values in self.scores.items()},
            "focus_z_um": self.focus_z_um,
        }


def _is_number(value: object) -> bool:
    """Whether `value` is a JSON number (json reads a boolean as one of Python's ints)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def parse_curve(record: object, line: int) -> LabelledCurve:
    """One JSONL record as a curve; CurvesFileError naming `line` and the fault."""

    def fail(why: str) -> CurvesFileError:
        return CurvesFileError(f"line {line}: {why}")

    if not isinstance(record, dict):
        raise fail("a field is a JSON object with z_um, scores and focus_z_um")
    missing = [key for key in ("z_um", "scores", "focus_z_um") if key not in record]
    if missing:
        raise fail(f"missing {', '.join(missing)}")
    scores = record["scores"]
    if not isinstance(scores, dict) or not scores:
        raise fail('"scores" must be an object {"METRIC": [score per z], ...}, not empty')
    number = record.get("field", line)
    if not isinstance(number, int) or isinstance(number, bool):
        raise fail(f'"field" must be an integer, got {number!r}')
    focus = record["focus_z_um"]
    if not _is_number(focus) or not math.isfinite(focus):
        raise fail(f'"focus_z_um" must be a finite number, got {focus!r}')
    for name in scores:
        if problem := metric_name_problem(name):
            raise fail(problem)
    # numpy would read "1.5" and true as numbers: a column written as text, said here
    lists = {'"z_um"': record["z_um"]} | {f"{name!r} scores": v for name, v in scores.items()}
    for what, values in lists.items():
        if not isinstance(values, list):
            raise fail(f"{what} must be a list of numbers, got {type(values).__name__}")
        strays = [value for value in values if not _is_number(value)]
        if strays:
            raise fail(f"{what} must be numbers, got {strays[0]!r}")
    try:
        raw_z = np.asarray(record["z_um"], dtype=np.float64)
        curves = {}
        for name, values in scores.items():
            z, curves[name] = validate_curve(raw_z, np.asarray(values, dtype=np.float64))
    except (ValueError, TypeError) as error:
        raise fail(str(error)) from None
    if not z[0] <= focus <= z[-1]:
        raise fail(f"focus_z_um {focus} lies outside the curve's z ({z[0]} .. {z[-1]} um)")
    return LabelledCurve(number, z, curves, float(focus))


def load_curves(path: Path) -> list[LabelledCurve]:
    """Every field of a JSONL curves file; CurvesFileError on the first bad line, when the
    file is not UTF-8 text, or when two lines name the same field."""
    curves: list[LabelledCurve] = []
    with path.open(encoding="utf-8") as lines:
        try:
            numbered = list(enumerate(lines, start=1))
        except UnicodeDecodeError:  # a binary file (an image), or text in another encoding
            raise CurvesFileError(f"{path}: not UTF-8 text (a curves file is JSON lines)") from None
    for line, text in numbered:
        if not text.strip():
            continue
        try:
            record = json.loads(text)
        except json.JSONDecodeError as error:
            raise CurvesFileError(f"line {line}: not JSON ({error.msg})") from None
        curves.append(parse_curve(record, line))
    numbers = [curve.number for curve in curves]
    if len(set(numbers)) != len(numbers):
        raise CurvesFileError(f"{path}: a field number appears twice")
    if not curves:
        raise CurvesFileError(f"{path}: no curves")
    return curves


def write_curves(path: Path, curves: Iterable[LabelledCurve]) -> None:
    """The curves as a JSONL file, one field a line (`load_curves` reads it back)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8") as out:
        for curve in curves:
            out.write(json.dumps(curve.to_json()) + "\n")


def wsi_curves(
    fields: Sequence[WsiField], metrics: Iterable[str] | None = None
) -> list[LabelledCurve]:
    """The shared WSI fields as labelled curves (z = WSI_STEP_UM x position), with every
    measure or only `metrics`."""
    out = []
    for field in fields:
        names = list(field.scores) if metrics is None else list(metrics)
        z_um = WSI_STEP_UM * np.arange(field.n_positions, dtype=np.float64)
        scores = {name: field.scores[name] for name in names}
        out.append(LabelledCurve(field.number, z_um, scores, float(z_um[field.label_index])))
    return out
