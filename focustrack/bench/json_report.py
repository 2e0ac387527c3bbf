"""The one way the benchmarks write their `--json` reports.

A figure with nothing to measure is NaN (a mean over no tiles) and an unbounded one inf;
Python's `json` writes them as bare `NaN` and `Infinity`, which are not JSON (a browser's
`JSON.parse` and `jq` refuse the file). They are written as `null`, and the dump refuses
any other non-finite number (`allow_nan=False`) rather than write an unreadable file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def finite_or_null(value: Any) -> Any:
    """`value` with every NaN or infinite float in it, in dicts, lists and tuples at any
    depth, replaced by None (JSON's null)."""
    if isinstance(value, float):  # numpy's float64 too: it is a float
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_null(item) for item in value]
    return value


def write_json(path: Path, report: Any) -> None:
    """Write `report` to `path` as indented JSON, NaN and inf as null, making its folder."""
    text = json.dumps(finite_or_null(report), indent=2, allow_nan=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n")
