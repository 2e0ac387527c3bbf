"""A slide's scale on the focus service's sigma, learnt from its innovations (adaptive R).

A focus metric new to a microscope may state a sigma several times too small; no
label says so, but the scan does: its measurements disagree with the filter's
predictions more than their stated sigmas allow. With innovation nu = z - prior mean,
prior variance P and stated sigma s scaled by k, nu**2 has expectation P + k**2 s**2,
so each measurement gives an estimate of k**2,

    q = (nu**2 - P) / s**2,

unbiased where the filter's P is right. `SigmaScale` pools them with `PRIOR_COUNT`
pseudo-measurements at k = 1, and only once the filter has been shown inconsistent: the
sum of the normalised innovations squared (NIS) of the measurements so far, each
chi-square with one degree of freedom where the sigmas are honest (and counted up to
`MAX_EVIDENCE_NIS`, so that one outlier is no evidence), stands above its `EVIDENCE`
quantile. A focus service whose sigma is honest keeps a scale of exactly 1. Each q
is capped at `MAX_SAMPLE` (one outlier must not set the scale), and the scale stays
within [1, `MAX_SCALE`]: it only widens a sigma found too small, never narrows one
(trusting a measurement more than its maker does is not this rule's to decide).

Gated-out measurements count too (their innovation is known): a 3x overconfident metric
would otherwise have its largest disagreements gated away and hide. The scale is the
slide's (its strategy's attribute, in its snapshots); a measurement without a sigma is
the filter's own business (its default R) and is left alone.
"""

from __future__ import annotations

import dataclasses
import math

from focustrack_core.domain import Measurement, Outcome
from focustrack_estimator.diagnostics import chi2_quantile

#: Pseudo-measurements at scale 1 that the estimate starts from.
PRIOR_COUNT = 5
#: A single measurement's estimate of the squared scale is capped here (an 8x miss: a
#: 3x overconfident metric's estimates pass whole but for 1 in 100).
MAX_SAMPLE = 64.0
#: The largest scale.
MAX_SCALE = 5.0
#: The scale moves once the measurements' disagreement is this unlikely under scale 1 ...
EVIDENCE = 0.999
#: ... each measurement's NIS counted up to this (3 sigmas): one outlier (a debris peak)
#: is not evidence against every other measurement's sigma.
MAX_EVIDENCE_NIS = 9.0


class SigmaScale:
    """The per-slide factor on measured sigmas (module docstring). `scale` starts at 1."""

    def __init__(self) -> None:
        self.n = 0
        self.sum_q = 0.0
        self.sum_nis = 0.0  # until engaged: the NIS with unscaled sigmas
        self.engaged = False

    @property
    def scale(self) -> float:
        """The factor applied to each measurement's sigma, in [1, MAX_SCALE]."""
        if not self.engaged:
            return 1.0
        squared = (PRIOR_COUNT + self.sum_q) / (PRIOR_COUNT + self.n)
        return min(max(math.sqrt(squared), 1.0), MAX_SCALE)

    def scaled(self, measurement: Measurement) -> Measurement:
        """The measurement with its sigma times `scale` (as it is; without a sigma)."""
        if measurement.sigma_um is None or self.scale == 1.0:
            return measurement
        return dataclasses.replace(measurement, sigma_um=measurement.sigma_um * self.scale)

    def learn(self, measurement: Measurement, outcome: Outcome) -> None:
        """Take one measurement's disagreement with the prediction: `measurement` as the
        focus service stated it, `outcome` of the filter given it scaled by `scale`."""
        nu, nis, sigma = outcome.innovation_um, outcome.nis, measurement.sigma_um
        if nu is None or nis is None or sigma is None or sigma <= 0.0 or nis <= 0.0:
            return
        used_r_um2 = (sigma * self.scale) ** 2
        prior_var_um2 = max(nu**2 / nis - used_r_um2, 0.0)
        self.sum_q += min(max((nu**2 - prior_var_um2) / sigma**2, 0.0), MAX_SAMPLE)
        self.n += 1
        if not self.engaged:
            self.sum_nis += min(nis, MAX_EVIDENCE_NIS)
            self.engaged = self.sum_nis > chi2_quantile(EVIDENCE, self.n)
