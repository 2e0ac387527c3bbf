"""A slide's diagnostics: pure functions of its history and its strategy's maps."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from focustrack_estimator.diagnostics import InnovationDiagnostics, innovation_diagnostics
from focustrack_estimator.lean import RiskSummary, summarise_risk
from focustrack_estimator.records import Logged
from focustrack_estimator.strategy import Strategy

#: Innovation lags the whiteness test pools (fewer when the scan is short).
MAX_LAG = 20


@dataclasses.dataclass(frozen=True)
class SlideDiagnostics:
    """Counts over a slide's acquisitions, its innovation statistics when there are enough,
    and its predicted out-of-focus risk where its strategy states one."""

    n_acquisitions: int
    n_measured: int  # acquisitions that asked for a best focus
    n_accepted: int  # measurements used as observations
    n_rejected: int  # measured, but not an observation: edge, flat, gated out
    innovations: InnovationDiagnostics | None
    innovations_note: str | None  # why `innovations` is None
    risk: RiskSummary | None
    sigma_scale: float = 1.0  # the slide's factor on measured sigmas (`sigma_scale`)


def diagnose(history: Sequence[Logged], strategy: Strategy) -> SlideDiagnostics:
    """Diagnostics from the accepted outcomes' innovations and NIS (S = innovation^2 / NIS).

    Gated-out measurements are counted as rejected but left out of the innovation
    statistics, which describe the filter's consistency on what it used.
    """
    n_measured = sum(logged.acquisition.measure for logged in history)
    n_accepted = sum(logged.outcome.accepted for logged in history)
    innovation_um, variance_um2 = [], []
    for logged in history:
        outcome = logged.outcome
        if not outcome.accepted or outcome.innovation_um is None or outcome.nis is None:
            continue
        innovation_um.append(outcome.innovation_um)
        # NIS = 0 only for a zero innovation, whose normalised value is 0 whatever S is.
        variance_um2.append(outcome.innovation_um**2 / outcome.nis if outcome.nis > 0 else 1.0)
    innovations, note = None, None
    n = len(innovation_um)
    if n < 3:
        note = f"{n} innovation(s) logged; at least 3 are needed"
    else:
        try:
            innovations = innovation_diagnostics(
                np.array(innovation_um), np.array(variance_um2), max_lag=min(MAX_LAG, n - 2)
            )
        except ValueError as error:  # a constant sequence has no autocorrelation
            note = str(error)
    return SlideDiagnostics(
        len(history),
        n_measured,
        n_accepted,
        n_measured - n_accepted,
        innovations,
        note,
        risk_summary(strategy),
        strategy.sigma_scale.scale,
    )


def risk_summary(strategy: Strategy) -> RiskSummary | None:
    """The strategy's predicted out-of-focus risk over its imaged tiles against the one it
    states (None where it predicts none)."""
    risk_map = strategy.focus_map().out_of_focus_risk
    if risk_map is None:
        return None
    return summarise_risk(
        risk_map, strategy.stated_risk, strategy.settings.dof_um, strategy.measurement_sigma_um
    )
