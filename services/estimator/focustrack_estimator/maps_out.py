"""A slide's focus map as the API serves it: JSON, CSV, .npy or a PNG heat map."""

from __future__ import annotations

import json
from typing import Literal

from focustrack_client import models as api
from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import layer_json, map_csv, map_layers, map_npy
from focustrack_estimator.heatmap import MAGMA, VIRIDIS, heat_map_png

MapFormat = Literal["json", "csv", "npy", "png"]

#: The media type of each format but JSON (the response model's own).
FILE_MEDIA = {
    "csv": "text/csv",
    "npy": "application/octet-stream",
    "png": "image/png",
}


def render_map(
    focus_map: FocusMap, grid: ScanGrid, map_format: MapFormat, title: str
) -> tuple[str | bytes, str]:
    """The map in `map_format`, and its media type; `title` names the PNG's heat map."""
    if map_format == "json":
        return map_json(focus_map, grid), "application/json"
    if map_format == "csv":
        content: str | bytes = map_csv(focus_map, grid)
    elif map_format == "npy":
        content = map_npy(focus_map)
    else:
        content = map_png(focus_map, title)
    return content, FILE_MEDIA[map_format]


def map_json(focus_map: FocusMap, grid: ScanGrid) -> str:
    """The JSON of `api.FocusMapOut`, written directly: validating and serialising 280 000
    floats through the model took seconds for a 200x200 slide (a test checks it validates)."""
    layers = map_layers(focus_map)
    fields = {"rows": str(grid.rows), "cols": str(grid.cols)}
    for name in api.FocusMapOut.model_fields.keys() - fields.keys():
        missing = getattr(focus_map, name) is None
        fields[name] = "null" if missing else layer_json(layers[name])
    ordered = (f"{json.dumps(name)}:{fields[name]}" for name in api.FocusMapOut.model_fields)
    return "{" + ",".join(ordered) + "}"


def map_png(focus_map: FocusMap, title: str) -> bytes:
    """A PNG heat map of the posterior focus map and its sigma, side by side (`heatmap`)."""
    layers = map_layers(focus_map)
    return heat_map_png(
        [
            ("posterior_um", layers["posterior_um"], VIRIDIS),
            ("posterior_sigma_um", layers["posterior_sigma_um"], MAGMA),
        ],
        title,
    )
