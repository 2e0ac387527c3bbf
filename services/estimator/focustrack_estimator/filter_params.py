"""The parameters every filter strategy's loop takes (`serpentine.SerpentineFilter`).

Pydantic models, one per layer of what a strategy offers: `RetryParams` (the search after
a stack without a peak), `LeanParams` (the lean rule: docs/lean.md) and `FilterParams`
(the loop's options whatever the filter: the NIS gate, the adaptive R, the square-root
form). Each field's type is an `Annotated` with its bounds and description, shared by the
strategies whose own models hold it (the estimator's API documents them from these).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from focustrack_client.models import MAX_FRAMES
from focustrack_core.domain import PAIR_FRAMES
from focustrack_estimator.lean import COARSE_STEP_UM, SHORT_FRAMES, SKIP_MODEL_TEMPERATURE
from focustrack_estimator.strategy import MAX_RETRIES, StrategyParams

MaxRetries = Annotated[
    int,
    Field(
        ge=0,
        le=MAX_RETRIES,
        description="Stacks taken after the first on a tile without a peak before the tile "
        "is given up (imaged at its prediction)",
    ),
]
RiskOutOfFocus = Annotated[
    float,
    Field(
        ge=0.0,
        lt=1.0,
        description="Share of tiles allowed outside the depth of field. 0: a stack of +/- "
        "k innovation sigmas on every tile; above 0, each tile's frames are chosen so that "
        "at most this share is imaged out of focus (the kept image alone, 3 frames or a "
        "full stack: `lean.choose_stack`)",
    ),
]
SkipSigmaScale = Annotated[
    float,
    Field(
        ge=1.0,
        description="Factor by which the lean rule widens the predicted sigma of a tile it "
        "would image without measuring it (`lean.skip_risk`)",
    ),
]
SkipModelTemperature = Annotated[
    float,
    Field(
        ge=1.0,
        le=1e3,
        description="Where a bank of models predicts a tile (kf-2d), the lean rule weighs "
        "its members for the risk of imaging the tile without measuring it by their "
        "likelihoods to the power 1/T (`bank.tempered_weights`): T = 1 is the bank's own "
        "blend, which trusts the best member after a row or two",
    ),
]
CoarseStepUm = Annotated[
    float,
    Field(
        gt=0.0,
        le=1e3,  # as a z-stack policy's step: beyond, a search leaves any stage's travel
        description="z step of the lean rule's coarse search where the prediction is far "
        "too unsure for fine stacks, um (`lean.coarse_stack`), at most 1000",
    ),
]
LookFirst = Annotated[
    bool,
    Field(
        description="Acquire a tile's first stack in two parts where its lowest frame lies "
        "near its centre: that frame alone, then (where the focus service sees something in "
        "view) the rest, which it reads with that frame as one curve: an empty tile costs "
        "one frame (`look_first.first_part`)",
    ),
]
ShortFrames = Annotated[
    int,
    Field(
        ge=PAIR_FRAMES,
        le=SHORT_FRAMES,
        description="Frames of the lean rule's short stack: 3 (the focus service reads a peak "
        "between the outer two), or 2 one z step apart, a pair, whose scores' ratio the focus "
        "service reads with the slide's learnt curve up to PAIR_REACH_UM beyond them (a peak "
        "beyond the frames is then imaged by one more frame there: docs/lean.md)",
    ),
]
MaxKeptPlanes = Annotated[
    int,
    Field(
        ge=1,
        le=MAX_FRAMES,
        description="With risk_out_of_focus set, most frames a measured tile keeps where its "
        "kept frame alone would exceed that risk, each within a depth of field of the next "
        "(`lean.kept_planes`): the tile is in focus when one of them is. A stack taken for "
        "them has at most the slide's max_frames",
    ),
]
GateNis = Annotated[
    float,
    Field(
        ge=0.0,
        description="NIS threshold of the outlier gate (0: no gating; chi-square with one "
        "degree of freedom for a consistent filter, `diagnostics.nis_gate`)",
    ),
]
GatePatience = Annotated[
    int,
    Field(
        ge=0,
        description="Measurements rejected by the gate in a row after which the next one is "
        "taken as a real step of the surface",
    ),
]
AdaptR = Annotated[
    bool,
    Field(description="Estimate the default measurement variance R online from the innovations"),
]
Sqrt = Annotated[
    bool, Field(description="Run the filter in square-root form (where the filter has one)")
]


class RetryParams(StrategyParams):
    """What every filter strategy takes: the search after a stack without a peak."""

    max_retries: MaxRetries = 3


class LeanParams(RetryParams):
    """The lean rule's parameters (`lean.choose_stack`, docs/lean.md): off by default."""

    risk_out_of_focus: RiskOutOfFocus = 0.0
    skip_sigma_scale: SkipSigmaScale = 1.0
    skip_model_temperature: SkipModelTemperature = SKIP_MODEL_TEMPERATURE
    coarse_step_um: CoarseStepUm = COARSE_STEP_UM
    max_kept_planes: MaxKeptPlanes = 1
    look_first: LookFirst = False
    short_frames: ShortFrames = SHORT_FRAMES


class FilterParams(LeanParams):
    """How the loop treats measurements, whatever the filter: retries, the lean rule, the
    NIS gate, the adaptive R and the square-root form (off by default: the thesis' filters).

    The loop (`SerpentineFilter`) reads its options from this model; a strategy whose
    parameters hold fewer of them runs with the others at these defaults (`of`).
    """

    gate_nis: GateNis = 0.0
    gate_patience: GatePatience = 1
    adapt_r: AdaptR = False
    sqrt: Sqrt = False

    @classmethod
    def of(cls, params: RetryParams) -> FilterParams:
        """The loop's options in a strategy's `params`: those it has, the others at their
        defaults."""
        return cls.model_validate(params.model_dump(include=set(cls.model_fields)))
