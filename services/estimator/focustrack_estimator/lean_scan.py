"""Strategies that take the fewest frames: `kf-2d-lean` (and the re-scan filter, `kf-rescan`).

`kf-2d-lean` is `kf-2d` (docs/spatial.md) whose tiles are acquired by the
risk rule of `lean.choose_stack`: the kept image alone where the prediction
is sure enough, else a short stack of 3 frames or a full stack, whichever is
cheaper in expected frames. `risk_out_of_focus` is the share of tiles allowed
outside the depth of field (docs/lean.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from focustrack_core.domain import SlideSettings
from focustrack_estimator.lean import COARSE_STEP_UM
from focustrack_estimator.spatial import RowBankFilter, kf_2d
from focustrack_estimator.strategy import Strategy

#: The stated risk of the lean strategies by default: at most 1% of tiles out of focus.
DEFAULT_RISK = 0.01

#: The most frames a lean strategy keeps of a tile by default: at the thesis' noise (1.5 um,
#: a depth of field of 1 um) 5 frames a depth of field apart hold all but 0.1% of tiles.
MAX_KEPT_PLANES = 5


def kf_2d_lean(
    settings: SlideSettings,
    *,
    risk_out_of_focus: float = DEFAULT_RISK,
    skip_sigma_scale: float = 1.0,
    coarse_step_um: float = COARSE_STEP_UM,
    max_retries: int = 3,
    max_kept_planes: int = MAX_KEPT_PLANES,
) -> RowBankFilter:
    """`kf-2d` with frames chosen per tile by the risk rule (`lean.choose_stack`), keeping
    up to `max_kept_planes` of a tile's frames where one is too unsure (`lean.kept_planes`)."""
    strategy = kf_2d(settings, max_retries=max_retries)
    # kf-2d builds its own FilterOptions; the lean rule's settings are more of them.
    strategy.options = replace(
        strategy.options,
        risk_out_of_focus=risk_out_of_focus,
        skip_sigma_scale=skip_sigma_scale,
        coarse_step_um=coarse_step_um,
        max_kept_planes=max_kept_planes,
    )
    strategy.name = "kf-2d-lean"
    return strategy


STRATEGIES: dict[str, Callable[..., Strategy]] = {"kf-2d-lean": kf_2d_lean}
