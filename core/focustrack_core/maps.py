"""A focus map's files: the layers every export has, as CSV and as a .npy table, and back.

The estimator serves these formats (`GET /v1/slides/{id}/map?format=csv|npy`) and
the scheduler writes them beside a scan, so both use this one definition.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np

from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid


def finite_or_none(value: float | None) -> float | None:
    """JSON has no NaN: a missing estimate is null."""
    return None if value is None or not math.isfinite(value) else float(value)


#: The layers of a focus map export, in this order (rows x cols; heights and sigmas in um,
#: the predicted out-of-focus risk a probability).
MAP_LAYERS = (
    "prior_um",
    "prior_sigma_um",
    "posterior_um",
    "posterior_sigma_um",
    "smoothed_um",
    "smoothed_sigma_um",
    "z_used_um",
    "out_of_focus_risk",
)


def map_layers(focus_map: FocusMap) -> dict[str, np.ndarray]:
    """Every layer of `MAP_LAYERS` as a (rows, cols) float array (NaN where there is none)."""
    shape = focus_map.posterior_um.shape
    return {
        name: np.full(shape, np.nan)
        if getattr(focus_map, name) is None
        else np.asarray(getattr(focus_map, name), dtype=float)
        for name in MAP_LAYERS
    }


def map_csv(focus_map: FocusMap, grid: ScanGrid) -> str:
    """One line per tile (row-major): row, col, stage x/y and every layer; empty for NaN."""
    # Column by column on Python floats (repr, as before): a loop per cell took seconds
    # for a 200x200 map on a loaded machine.
    rows, cols = np.divmod(np.arange(grid.rows * grid.cols), grid.cols)
    columns = [
        [str(i) for i in rows.tolist()],
        [str(i) for i in cols.tolist()],
        [repr(v) for v in (grid.origin_x_um + cols * grid.pitch_um).tolist()],
        [repr(v) for v in (grid.origin_y_um + rows * grid.pitch_um).tolist()],
    ]
    columns += [
        [repr(v) if math.isfinite(v) else "" for v in layer.ravel().tolist()]
        for layer in map_layers(focus_map).values()
    ]
    lines = [",".join(("row", "col", "stage_x_um", "stage_y_um", *MAP_LAYERS))]
    lines += map(",".join, zip(*columns, strict=True))
    return "\n".join(lines) + "\n"


def layer_json(layer: np.ndarray) -> str:
    """A (rows, cols) float layer as a JSON array of rows, null where it is not finite."""
    # json's C encoder on the whole list writes NaN and infinities as bare words; no float
    # it writes contains them otherwise. Ten times faster than a null check per value.
    text = json.dumps(np.asarray(layer, dtype=float).tolist())
    return text.replace("-Infinity", "null").replace("Infinity", "null").replace("NaN", "null")


def map_npy(focus_map: FocusMap) -> bytes:
    """A .npy file: a (rows, cols) structured array with one float64 field per layer."""
    layers = map_layers(focus_map)
    table = np.empty(focus_map.posterior_um.shape, dtype=[(name, "<f8") for name in MAP_LAYERS])
    for name in MAP_LAYERS:
        table[name] = layers[name]
    buffer = io.BytesIO()
    np.save(buffer, table, allow_pickle=False)
    return buffer.getvalue()


def focus_map_of_npy(content: bytes) -> FocusMap:
    """The focus map of a `map_npy` file: smoothed layers None when all NaN, the risk None
    in a file written before it was a layer."""
    table = np.load(io.BytesIO(content), allow_pickle=False)
    optional = {
        name: None if np.all(np.isnan(table[name])) else np.array(table[name])
        for name in ("smoothed_um", "smoothed_sigma_um")
    }
    if "out_of_focus_risk" in (table.dtype.names or ()):
        optional["out_of_focus_risk"] = np.array(table["out_of_focus_risk"])
    return FocusMap(
        prior_um=np.array(table["prior_um"]),
        prior_sigma_um=np.array(table["prior_sigma_um"]),
        posterior_um=np.array(table["posterior_um"]),
        posterior_sigma_um=np.array(table["posterior_sigma_um"]),
        z_used_um=np.array(table["z_used_um"]),
        **optional,
    )
