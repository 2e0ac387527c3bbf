"""How many tiles a scan has in focus, against the instrument's truth (evaluation only)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from focustrack_core.domain import kept_in_focus
from focustrack_scheduler.tally import Tile


@dataclass(frozen=True)
class InFocusScore:
    """A tile is in focus when a frame it keeps lies within `dof_um` / 2 of its true focus
    `truth_um` (rows, cols), um."""

    truth_um: np.ndarray
    dof_um: float

    def tiles(self, kept: Mapping[Tile, float], planes: Mapping[Tile, Sequence[float]]) -> int:
        """Tiles in focus: `kept` holds each tile's image z, `planes` the z of the frames a
        tile keeps besides (its image among them), um."""
        if not kept:
            return 0
        # Vectorised over the images (the progress bar asks after every tile: a loop in
        # Python over 40 000 tiles each time would be quadratic); the few tiles that keep
        # planes are then judged on all of them (their planes hold their image too).
        rows, cols = np.array(list(kept)).T
        z_um = np.array(list(kept.values()))
        truth_um = self.truth_um
        n_in_focus = int(np.count_nonzero(np.abs(z_um - truth_um[rows, cols]) <= self.dof_um / 2))
        for tile, planes_um in planes.items():
            if tile in kept:
                image_in_focus = kept_in_focus([kept[tile]], truth_um[tile], self.dof_um)
                n_in_focus += kept_in_focus(planes_um, truth_um[tile], self.dof_um) - image_in_focus
        return n_in_focus
