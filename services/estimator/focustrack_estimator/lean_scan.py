"""Strategies that take the fewest frames: `kf-2d-lean` (and the re-scan filter, `kf-rescan`).

`kf-2d-lean` is `kf-2d` (docs/spatial.md) whose tiles are acquired by the
risk rule of `lean.choose_stack`: the kept image alone where the prediction
is sure enough, else a short stack of 3 frames or a full stack, whichever is
cheaper in expected frames. `risk_out_of_focus` is the share of tiles allowed
outside the depth of field (docs/lean.md).
"""

from __future__ import annotations

from typing import Any

from focustrack_core.domain import SlideSettings
from focustrack_estimator.filter_params import LeanParams, MaxKeptPlanes, RiskOutOfFocus
from focustrack_estimator.spatial import RowBankFilter, RowBankParams, kf_2d_cost
from focustrack_estimator.strategy import Cost, StrategyEntry
from focustrack_estimator.time_state import RevisitParams

#: The stated risk of the lean strategies by default: at most 1% of tiles out of focus.
DEFAULT_RISK = 0.01

#: The most frames a lean strategy keeps of a tile by default: at the thesis' noise (1.5 um,
#: a depth of field of 1 um) 5 frames a depth of field apart hold all but 0.1% of tiles.
MAX_KEPT_PLANES = 5


class Kf2dLeanParams(LeanParams, RevisitParams):
    """kf-2d-lean: kf-2d at its default bank, each tile's frames chosen by the risk rule
    (with a time state: the instrument's drift estimated too, `time_state`)."""

    risk_out_of_focus: RiskOutOfFocus = DEFAULT_RISK
    max_kept_planes: MaxKeptPlanes = MAX_KEPT_PLANES


def kf_2d_lean(settings: SlideSettings, params: Kf2dLeanParams) -> RowBankFilter:
    """`kf-2d` with frames chosen per tile by the risk rule (`lean.choose_stack`), keeping
    up to `max_kept_planes` of a tile's frames where one is too unsure (`lean.kept_planes`)."""
    return RowBankFilter(settings, RowBankParams(), params, name="kf-2d-lean")


def kf_2d_lean_cost(settings: SlideSettings, params: Kf2dLeanParams) -> Cost:
    """kf-2d's at its default bank: the lean rule's parameters only pick frames."""
    return kf_2d_cost(settings, RowBankParams())


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "kf-2d-lean": StrategyEntry(Kf2dLeanParams, kf_2d_lean, kf_2d_lean_cost),
}
