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

from focustrack_estimator.lean import COARSE_STEP_UM
from focustrack_estimator.spatial import RowBankFilter, kf_2d
from focustrack_estimator.strategy import SlideSettings, Strategy

#: The stated risk of the lean strategies by default: at most 1% of tiles out of focus.
DEFAULT_RISK = 0.01


def kf_2d_lean(
    settings: SlideSettings,
    *,
    risk_out_of_focus: float = DEFAULT_RISK,
    skip_sigma_scale: float = 1.0,
    coarse_step_um: float = COARSE_STEP_UM,
    max_retries: int = 3,
) -> RowBankFilter:
    """`kf-2d` with frames chosen per tile by the risk rule (`lean.choose_stack`)."""
    strategy = kf_2d(settings, max_retries=max_retries)
    # kf-2d builds its own FilterOptions; the lean rule's settings are more of them.
    strategy.options = replace(
        strategy.options,
        risk_out_of_focus=risk_out_of_focus,
        skip_sigma_scale=skip_sigma_scale,
        coarse_step_um=coarse_step_um,
    )
    strategy.name = "kf-2d-lean"
    return strategy


STRATEGIES: dict[str, Callable[..., Strategy]] = {"kf-2d-lean": kf_2d_lean}
