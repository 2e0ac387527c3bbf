"""A bank of models run at once and blended by likelihood: multiple-model adaptive estimation.

The thesis' proposed future work (section 5, "MMAE"): a slide is flat in one
place and bent in another, and no single model or noise level fits it all.
`ModelBank` runs several `PathFilter`s side by side on the same measurements
and blends their estimates with the posterior probability of each model,

    w_j <- w_j N(y_j; 0, S_j) / sum_i w_i N(y_i; 0, S_i),

y_j and S_j being member j's innovation and its predicted variance. The
likelihood is made robust by adding to every member's density the same small
density: that of the widest member at NIS = `nis_clip`. An outlier, which no
member predicts, then leaves the weights almost as they were instead of handing
them to the member with the widest prior. The weights are then held above
`weight_floor` (and renormalised), so that a model that was wrong for the
last hundred tiles can take over within a few tiles when the surface changes;
FilterPy's `MMAEFilterBank` has no floor and lets the weights collapse
(ENGINEERING_NOTES). The members do not mix their states (unlike an IMM), so
members of different state dimensions can share a bank.

Members with the same model at several process-noise levels make the bank a
maximum-likelihood estimator of Q (the weights are the posterior of q over the
grid): this is the adaptive process noise of docs/estimators.md, one default
configuration for slides of any roughness.

Smoothing: each member is RTS-smoothed and the smoothed heights are blended
with the final weights (for models fixed over the slide these are the
posterior model probabilities given every measurement, which makes the blend
the exact smoothed mixture; with the floor it is an approximation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import Field

from focustrack_core.domain import SlideSettings
from focustrack_core.geometry import Step
from focustrack_estimator.filter_params import FilterParams, GateNis
from focustrack_estimator.kalman_strategies import (
    KalmanStrategy,
    PathEstimator,
    PathFilter,
    QHeightUm2,
    path_cost,
)
from focustrack_estimator.models import DirectionAwareModel
from focustrack_estimator.strategy import StrategyEntry


def mixture(
    means_um: np.ndarray, vars_um2: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean (um) and variance (um^2) of Gaussian mixtures, member axis first.

    `weights` (n_members,); `means_um` and `vars_um2` (n_members, ...) are the
    members' estimates of the same quantities; the results have shape (...).
    """
    mean_um = np.tensordot(weights, means_um, axes=1)
    return mean_um, np.tensordot(weights, vars_um2 + (means_um - mean_um) ** 2, axes=1)


def tempered_weights(log_weights: np.ndarray, temperature: float) -> np.ndarray:
    """Model probabilities from log likelihoods (n_members,), each raised to 1/`temperature`.

    At 1 these are the bank's Bayesian weights; above, a power posterior: the evidence
    counts 1/T as much, so members the data have not ruled out keep a share. Where no
    member is the truth, Bayesian weights concentrate on one member faster than its
    predictions deserve (the lean rule's risk: `lean.SKIP_MODEL_TEMPERATURE`).
    """
    scaled = (log_weights - log_weights.max()) / temperature
    weights = np.exp(scaled)
    return weights / weights.sum()


class ModelBank(PathEstimator):
    """Several `PathFilter`s on the same measurements, blended by their likelihoods.

    `weights` (n_members,) are the current model probabilities, each at least
    `weight_floor`; `nis_clip` sets the density floor of the robust likelihood.
    """

    def __init__(
        self, members: Sequence[PathFilter], *, weight_floor: float, nis_clip: float
    ) -> None:
        if not members:
            raise ValueError("a model bank needs at least one member")
        if not 0.0 <= weight_floor < 1.0 / len(members):
            raise ValueError(
                f"weight_floor must be in [0, 1/{len(members)}) for {len(members)} members, "
                f"got {weight_floor}"
            )
        if not nis_clip > 0:
            raise ValueError(f"nis_clip must be positive, got {nis_clip}")
        self.members = list(members)
        self.nis_clip = nis_clip
        self.weight_floor = weight_floor
        self.weights = np.full(len(members), 1.0 / len(members))

    def _heights(self) -> tuple[np.ndarray, np.ndarray]:
        heights = np.array([member.height for member in self.members])
        return heights[:, 0], heights[:, 1]

    @property
    def height(self) -> tuple[float, float]:
        mean_um, var_um2 = mixture(*self._heights(), self.weights)
        return float(mean_um), float(var_um2)

    def predict(self, step: Step, dt_s: float = 0.0) -> None:
        for member in self.members:
            member.predict(step, dt_s)

    def update(self, z_um: float, R_um2: float) -> None:
        means_um, vars_um2 = self._heights()
        innovation_var_um2 = vars_um2 + R_um2
        nis = (z_um - means_um) ** 2 / innovation_var_um2
        density = np.exp(-0.5 * nis) / np.sqrt(2.0 * math.pi * innovation_var_um2)
        floor = math.exp(-0.5 * self.nis_clip) / math.sqrt(2.0 * math.pi * innovation_var_um2.max())
        weights = self.weights * (density + floor)
        weights = np.maximum(weights / weights.sum(), self.weight_floor)
        self.weights = weights / weights.sum()
        for member in self.members:
            member.update(z_um, R_um2)

    def skip(self) -> None:
        for member in self.members:
            member.skip()

    def inflate(self, var_um2: float) -> None:
        for member in self.members:
            member.inflate(var_um2)

    def smoothed(self) -> tuple[np.ndarray, np.ndarray]:
        smoothed = [member.smoothed() for member in self.members]
        means_um = np.array([mean for mean, _ in smoothed])  # (n_members, n_tiles)
        vars_um2 = np.array([var for _, var in smoothed])
        return mixture(means_um, vars_um2, self.weights)


#: Members of the `kf-mmae` bank: two gradient noises, each with and without height noise.
MMAE_MEMBERS = 4


class KfMmaeParams(FilterParams):
    """kf-mmae: a bank of four direction-aware filters blended by likelihood (MMAE).

    Defaults chosen on training seeds (docs/estimators.md); its gate is on by default.
    """

    gate_nis: GateNis = 25.0
    q: float = Field(
        1e-4,
        ge=0.0,
        description="Spectral density of the lively members' gradient noise, um^2/tile^3 "
        "(the stiff members': q / q_spread)",
    )
    q_spread: float = Field(
        3.0, ge=1.0, description="Ratio of the lively members' gradient noise to the stiff ones'"
    )
    q_height_um2: QHeightUm2 = 0.3
    weight_floor: float = Field(
        1e-3,
        ge=0.0,
        lt=1.0 / MMAE_MEMBERS,
        description="Least weight of a member, so that a model can take over within a few "
        "tiles when the surface changes",
    )
    nis_clip: float = Field(
        9.0,
        gt=0.0,
        description="NIS at which the widest member's density floors every member's "
        "likelihood (an outlier then leaves the weights almost as they were)",
    )


def kf_mmae(settings: SlideSettings, params: KfMmaeParams) -> KalmanStrategy:
    """A bank of four direction-aware filters: two gradient noises, with and without height noise.

    Members: `DirectionAwareModel(q', q_height_um2=h)` (full update) for q' in
    {q / q_spread, q} (um^2/tile^3) and h in {0, q_height_um2} (um^2): a
    stiff and a lively gradient, each with and without a height that may jump
    (steps, rough smears). Gating and the adaptive R act on the blended
    prediction.
    """
    models = [
        DirectionAwareModel(q_member, q_height_um2=height_um2, partitioned=False)
        for q_member in (params.q / params.q_spread, params.q)
        for height_um2 in (0.0, params.q_height_um2)
    ]
    bank = ModelBank(
        [PathFilter(model, settings, sqrt=params.sqrt) for model in models],
        weight_floor=params.weight_floor,
        nis_clip=params.nis_clip,
    )
    return KalmanStrategy(settings, bank, name="kf-mmae", options=params)


STRATEGIES: dict[str, StrategyEntry[Any]] = {
    "kf-mmae": StrategyEntry(KfMmaeParams, kf_mmae, path_cost(MMAE_MEMBERS))
}
