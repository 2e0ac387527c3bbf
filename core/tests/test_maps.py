"""The focus map's file formats: the JSON layer and the CSV, on awkward values."""

from __future__ import annotations

import io
import json
import math

import numpy as np

from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import MAP_LAYERS, focus_map_of_npy, layer_json, map_csv, map_npy


def test_a_json_layer_has_null_where_the_value_is_not_finite() -> None:
    layer = np.array([[1.5, np.nan, -0.0], [np.inf, -np.inf, 1e-300]])
    assert json.loads(layer_json(layer)) == [[1.5, None, -0.0], [None, None, 1e-300]]


def test_the_csv_has_a_line_per_tile_with_exact_values_and_empty_cells_for_nan() -> None:
    grid = ScanGrid(2, 3, pitch_um=0.1, origin_x_um=0.2, origin_y_um=-5.0)
    layer = np.array([[0.1, 2.0 / 3.0, np.nan], [-1.0, 1e-17, 3.0]])
    focus_map = FocusMap(layer, layer, layer, layer, layer)  # smoothed layers None
    lines = map_csv(focus_map, grid).splitlines()
    assert lines[0].split(",") == ["row", "col", "stage_x_um", "stage_y_um", *MAP_LAYERS]
    assert len(lines) == 1 + 6
    cells = [line.split(",") for line in lines[1:]]
    assert [c[:2] for c in cells] == [
        ["0", "0"],
        ["0", "1"],
        ["0", "2"],
        ["1", "0"],
        ["1", "1"],
        ["1", "2"],
    ]
    # Stage positions and values as Python writes the floats (repr round-trips exactly).
    assert cells[1][2:4] == [repr(0.2 + 1 * 0.1), repr(-5.0 + 0 * 0.1)]
    assert cells[1][4] == repr(2.0 / 3.0) and float(cells[1][4]) == 2.0 / 3.0
    assert cells[2][4] == "" and cells[4][4] == "1e-17"
    assert cells[0][8:10] == ["", ""]  # no smoothed layers: empty cells
    table = np.genfromtxt(io.StringIO("\n".join(lines)), delimiter=",", names=True)
    assert math.isnan(table["prior_um"][2])


def test_the_npy_table_round_trips_the_risk_layer_and_reads_files_written_before_it() -> None:
    grid = ScanGrid(2, 2, pitch_um=100.0)
    focus_map = FocusMap.empty(grid)
    assert focus_map.out_of_focus_risk is not None
    focus_map.posterior_um[:] = [[1.0, 2.0], [3.0, 4.0]]
    focus_map.out_of_focus_risk[0] = [0.25, 0.001]  # row 1 not imaged: NaN
    read = focus_map_of_npy(map_npy(focus_map))
    assert read.out_of_focus_risk is not None
    np.testing.assert_array_equal(read.out_of_focus_risk, focus_map.out_of_focus_risk)
    np.testing.assert_array_equal(read.posterior_um, focus_map.posterior_um)

    # a table written before the layer existed: no risk, the other layers as they were
    table = np.load(io.BytesIO(map_npy(focus_map)))
    older = [name for name in MAP_LAYERS if name != "out_of_focus_risk"]
    buffer = io.BytesIO()
    np.save(buffer, table[older].astype([(name, "<f8") for name in older]))
    legacy = focus_map_of_npy(buffer.getvalue())
    assert legacy.out_of_focus_risk is None
    np.testing.assert_array_equal(legacy.posterior_um, focus_map.posterior_um)
