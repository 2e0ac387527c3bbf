"""The figures of a finished scan (``report.json``): images, scan time, focus against truth."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from focustrack_core.domain import FocusMap, Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_scheduler.in_focus import InFocusScore
from focustrack_scheduler.tally import ScanTally


def mean_abs_error_um(estimate_um: np.ndarray, truth_um: np.ndarray) -> float | None:
    """Mean |estimate - truth| over the tiles that have an estimate (None if none has)."""
    error = np.abs(estimate_um - truth_um)
    return float(np.nanmean(error)) if np.isfinite(error).any() else None


def predicted_in_focus_fraction(focus_map: FocusMap) -> float | None:
    """The share of imaged tiles the estimator expects in focus: 1 - their mean predicted
    out-of-focus risk (None where it states none)."""
    risk = focus_map.out_of_focus_risk
    if risk is None or not np.isfinite(risk).any():
        return None
    return 1.0 - float(np.nanmean(risk))


def scan_report(
    tally: ScanTally,
    state: Mapping[str, Any],
    grid: ScanGrid,
    focus_map: FocusMap,
    truth_um: np.ndarray | None,
    dof_um: float,
    wall_time_s: Mapping[str, float],
    focus_results_rejected: int,
    mosaic: str | None,
) -> dict[str, Any]:
    """The report of a scan: `tally` of its log, `state` of its scan.json, the estimator's
    `focus_map` and the instrument's `truth_um` (rows, cols; None: no in-focus figures),
    its wall-time split, the focus results rejected (no trusted tag) and its mosaic file."""
    n_images = tally.n_images
    in_focus = None
    if truth_um is not None:
        in_focus = InFocusScore(truth_um, dof_um).tiles(tally.kept, tally.planes) / grid.n_tiles
    return {
        "instrument": state.get("instrument"),
        "slide": state.get("slide"),
        "strategy": state.get("strategy"),
        "estimator": state.get("estimator"),
        "estimator_slide_id": state.get("slide_id"),
        "rows": grid.rows,
        "cols": grid.cols,
        "tiles_imaged": int(np.isfinite(tally.z_kept_um(grid)).sum()),
        "acquisitions": len(tally.acquisitions),
        "retries": sum(entry["purpose"] == Purpose.RETRY for entry in tally.acquisitions),
        "images_acquired": n_images,
        "images_per_tile": n_images / grid.n_tiles,
        "most_images_on_a_tile": int(tally.images_per_tile(grid).max()),
        # what the focus service said of the tiles: a device whose images never change with
        # z (an empty slide, a camera that sees no specimen) ends with every tile here
        "tiles_flagged": tally.flag_counts(),
        "tiles_without_focus": len(tally.tiles_without_focus()),
        "frames_kept_per_tile": tally.frames_kept / grid.n_tiles,
        "scan_time_s": tally.scan_time_s,
        "dof_um": dof_um,
        "in_focus_fraction": in_focus,
        "predicted_in_focus_fraction": predicted_in_focus_fraction(focus_map),
        "mae_um": None if truth_um is None else mean_abs_error_um(focus_map.posterior_um, truth_um),
        "prior_mae_um": None
        if truth_um is None
        else mean_abs_error_um(focus_map.prior_um, truth_um),
        # phase stacks (--phase): not in the figures above, which compare focus strategies
        "tiles_with_phase": len(tally.phase),
        # tiles whose phase was asked for, taken or not (no phase service, no result)
        "tiles_phase_asked": len({(entry["row"], entry["col"]) for entry in tally.phase_stacks}),
        "phase_images_acquired": sum(entry["n_frames"] for entry in tally.phase_stacks),
        "phase_scan_time_s": float(sum(entry["scan_time_s"] for entry in tally.phase_stacks)),
        "wall_time_s": dict(wall_time_s),
        "focus_results_rejected": focus_results_rejected,
        "mosaic": mosaic,
    }
