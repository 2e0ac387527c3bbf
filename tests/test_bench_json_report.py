"""The benchmarks' one JSON writer: NaN and infinities are null, the file plain JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from focustrack.bench.json_report import finite_or_null, write_json


def _strict(text: str) -> object:
    """The file as a strict JSON reader (JavaScript's JSON.parse) reads it."""

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_at_any_depth_are_written_as_null(tmp_path: Path) -> None:
    report = {
        "mean": math.nan,
        "rows": [1.5, math.inf, {"deep": (np.float64("nan"), -math.inf, 2)}],
        "name": "x",
        "none": None,
    }
    out = tmp_path / "made" / "report.json"  # its folder made too
    write_json(out, report)
    assert out.read_text().endswith("}\n")
    assert _strict(out.read_text()) == {
        "mean": None,
        "rows": [1.5, None, {"deep": [None, None, 2]}],
        "name": "x",
        "none": None,
    }


def test_finite_values_are_left_as_they_are() -> None:
    value = {"a": [0.0, -1e300, 3], "b": {"c": "nan", "d": True}}
    assert finite_or_null(value) == value
