"""Pictures of a finished scan (matplotlib, imported by the writers that need it only)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure

from focustrack_core.domain import FocusMap

#: The 2x2 panels' margins and gaps (fractions of the figure): fixed rather than a layout
#: engine, whose "constrained" solver took 0.75 s of the plot's 1.5 s at every scan's end.
_PANEL_MARGINS = {
    "left": 0.06,
    "right": 0.97,
    "bottom": 0.06,
    "top": 0.91,
    "wspace": 0.3,
    "hspace": 0.3,
}


def write_plots(
    path: Path,
    focus_map: FocusMap,
    truth_um: np.ndarray | None,
    images_per_tile: np.ndarray,
    title: str,
) -> Path:
    """True surface, estimated (posterior) map, error map and images per tile, as one PNG."""
    figure = Figure(figsize=(11, 9))
    FigureCanvasAgg(figure)
    axes = figure.subplots(2, 2, gridspec_kw=_PANEL_MARGINS).ravel()
    posterior_um = np.ma.masked_invalid(focus_map.posterior_um)
    heights = [posterior_um] + ([truth_um] if truth_um is not None else [])
    low_um = float(min(np.ma.min(h) for h in heights))
    high_um = float(max(np.ma.max(h) for h in heights))
    panels: list[tuple[Any, str, str, str, dict[str, Any]]] = [
        (posterior_um, "estimated focus map (posterior)", "um", "viridis", {}),
        (images_per_tile, "images per tile", "images", "cividis", {}),
    ]
    if truth_um is not None:
        error_um = np.ma.masked_invalid(focus_map.posterior_um - truth_um)
        limit_um = max(float(np.ma.max(np.abs(error_um))), 1e-3)
        norm = TwoSlopeNorm(0.0, -limit_um, limit_um)
        panels.insert(0, (truth_um, "true focus surface", "um", "viridis", {}))
        panels.insert(2, (error_um, "error: posterior - truth", "um", "RdBu_r", {"norm": norm}))
    for ax, (values, name, unit, cmap, extra) in zip(axes, panels, strict=False):
        if unit == "um" and "norm" not in extra:
            extra = {"vmin": low_um, "vmax": high_um}
        image = ax.imshow(values, cmap=cmap, origin="upper", **extra)
        ax.set(title=name, xlabel="col (x)", ylabel="row (y)")
        figure.colorbar(image, ax=ax, label=unit)
    for ax in axes[len(panels) :]:
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no truth from the instrument", ha="center", va="center")
    figure.suptitle(title)
    figure.savefig(path, dpi=90)
    return path
