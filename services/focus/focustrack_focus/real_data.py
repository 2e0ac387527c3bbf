"""Readers of the real microscope data the focus maths is checked on, each labelled by a person.

The folders of ../shared/data/real (its README says where each comes from):
`lip_smear_zstack/` and `yeast_brightfield_zstack/` are z-stacks with a labelled focus
plane, `wsi_focus_curves/` the focus curves of a whole-slide-imaging microscope with a
labelled best position. `focustrack bench focus` and the focus service's tests read them;
`calibration` learns a metric's constants from the curves.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tifffile

#: The yeast stack's focus plane (the source project's label, README of its folder).
YEAST_FOCUS_PLANE = 17
#: The z step of the WSI curves (um per motor step, the authors' later code).
WSI_STEP_UM = 0.5


def load_smear(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The lip smear stack: planes (n, h, w, 3) cropped to a common centre, and plane index (n,)."""
    planes = sorted(folder.glob("*.bmp"), key=lambda path: int(path.stem))
    images: list[np.ndarray] = [cv2.imread(str(path), cv2.IMREAD_COLOR_RGB) for path in planes]  # type: ignore[misc]
    height = min(image.shape[0] for image in images)
    width = min(image.shape[1] for image in images)

    def centre(image: np.ndarray) -> np.ndarray:
        y0 = (image.shape[0] - height) // 2
        x0 = (image.shape[1] - width) // 2
        return image[y0 : y0 + height, x0 : x0 + width]

    return np.stack([centre(image) for image in images]), np.array(
        [int(p.stem) for p in planes], dtype=np.float64
    )


def load_yeast(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The yeast stack (34, 63, 60) uint16 and its z (um, 0.3 um steps, plane 0 at 0)."""
    frames = tifffile.imread(folder / "zstack.tif")
    return frames, 0.3 * np.arange(frames.shape[0])


@dataclass(frozen=True)
class WsiField:
    """One field: scores (100,) per measure name, and the hand label (position index)."""

    number: int
    scores: dict[str, np.ndarray]
    label_index: int

    @property
    def n_positions(self) -> int:
        return next(iter(self.scores.values())).size


def load_wsi_fields(folder: Path) -> list[WsiField]:
    """The 20 fields of `wsi_focus_curves/` (groupNN.json), in order."""
    fields = []
    for path in sorted(folder.glob("group*.json")):
        data = json.loads(path.read_text())
        positions = sorted(data["positions"], key=lambda p: p["pos_idx"])
        names = positions[0]["focus_measures"]
        scores = {
            name: np.array([p["focus_measures"][name] for p in positions], dtype=np.float64)
            for name in names
        }
        fields.append(WsiField(int(path.stem.removeprefix("group")), scores, data["pos_peak_idx"]))
    return fields
