"""Request and response bodies of the estimator's REST API (pydantic), units in every name.

These models are the API's contract: the estimator service validates its
requests and builds its replies with them, and lab software gets them from the
client (`focustrack_client`), so both sides parse the same JSON the same way.
They depend on pydantic only.

Validation happens here, at the edge: numbers must be finite and within
sane bounds (so no filter ever sees NaN, infinity or a 1e308 um height),
sigmas positive, grids bounded, unknown fields rejected (a typo is an error,
not a silently ignored setting). Checks that need the slide (tile inside its
grid, the sequence asked for) are the estimator's, in its `slide.py` (`Slide.measure`).
"""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Any, Self

from pydantic import BaseModel, ConfigDict, Field, Strict, model_validator


class FocusFlag(StrEnum):
    """Quality flags of a best focus, as JSON spells the proto enum `focustrack.v1.FocusFlag`."""

    EDGE_LOW = "edge_low"  # the peak lies below the stack: extend downwards
    EDGE_HIGH = "edge_high"  # the peak lies above the stack: extend upwards
    FLAT = "flat"  # no peak in the curve (no contrast): no measurement
    EMPTY = "empty"  # with FLAT: nothing in view in any frame
    MULTI_PEAK = "multi_peak"  # more than one peak: the measurement is less certain
    AMBIGUOUS = "ambiguous"  # the chosen peak not clearly the focus (two peaks, or noise)
    VALLEY = "valley"  # with AMBIGUOUS: a sharp contrast minimum between two maxima (unstained)


class Purpose(StrEnum):
    """Why an acquisition is made."""

    SCAN = "scan"  # image the tile (and measure its focus where asked)
    SURVEY = "survey"  # a survey point of a focus-map strategy, before the scan
    RETRY = "retry"  # the same tile again, after an edge peak or a flat curve
    PLANES = "planes"  # more frames of a measured tile, kept where one is too unsure
    REVISIT = "revisit"  # a tile measured before, measured again to track the focus drift
    LASER = "laser"  # a reading of the reflection autofocus (the coverslip's height), no image


#: Largest grid side and tile count a slide may have (a 25 x 75 mm slide at 100 um tiles
#: is 250 x 750 = 187 500 tiles; the strategies keep per-tile maps in memory).
MAX_GRID_SIDE = 1000
MAX_TILES = 250_000
#: Bounds on heights and lengths, in um: a metre either way is no microscope.
MAX_ABS_UM = 1e6
#: Most frames a z-range policy may ask for in one stack.
MAX_FRAMES = 1001

#: Smallest standard deviation (or depth of field) a slide or measurement may state, in um:
#: a nanometre is below any optical focus measurement, and a smaller one (1e-300) makes
#: the filters' covariances singular.
MIN_SIGMA_UM = 1e-3

#: The strategy parameters that carry a slide's prior map (kf-rescan): its heights and their
#: sigmas, um, row after row. `PUT /v1/slides/{id}/prior` sets them from an .npy file.
PRIOR_MAP_PARAM = "prior_map_um"
PRIOR_SIGMA_PARAM = "prior_map_sigma_um"

#: Slides per page of `GET /v1/slides`: by default, and at most.
DEFAULT_PAGE_SLIDES = 100
MAX_PAGE_SLIDES = 1000
#: The header of a page of `GET /v1/slides` that holds the cursor of the next page (absent
#: on the last page), beside the `Link: <...>; rel="next"` header (RFC 8288) with its URL.
NEXT_CURSOR_HEADER = "X-Next-Cursor"
#: The header of a page of slides naming those left out because this version of the
#: service cannot read their stored configuration (another version's, or a damaged one).
UNREADABLE_SLIDES_HEADER = "X-Unreadable-Slides"
#: Most values a list parameter may hold to be shown in the slide listing: a longer one
#: (a prior map) is left out of it and named in `omitted_params`.
MAX_LISTED_VALUES = 16

Height = Annotated[float, Field(ge=-MAX_ABS_UM, le=MAX_ABS_UM)]
Length = Annotated[float, Field(gt=0, le=MAX_ABS_UM)]
Sigma = Annotated[float, Field(ge=MIN_SIGMA_UM, le=MAX_ABS_UM)]
#: A strategy parameter: a scalar, a list of numbers (a bank's grid), or None (the default).
ParamValue = bool | int | float | str | list[float] | None
#: Not strict: flags arrive as JSON strings, and strict mode takes only enum members.
Flag = Annotated[FocusFlag, Strict(False)]


class _Model(BaseModel):
    model_config = ConfigDict(allow_inf_nan=False, extra="forbid", strict=True)


class Grid(_Model):
    """The tile grid: tile (0, 0) is centred at the origin, tiles `pitch_um` apart."""

    rows: int = Field(ge=1, le=MAX_GRID_SIDE)
    cols: int = Field(ge=1, le=MAX_GRID_SIDE)
    pitch_um: Length = 200.0
    origin_x_um: Height = 0.0
    origin_y_um: Height = 0.0

    @model_validator(mode="after")
    def _bounded(self) -> Self:
        if self.rows * self.cols > MAX_TILES:
            raise ValueError(
                f"grid {self.rows}x{self.cols} has {self.rows * self.cols} tiles; "
                f"at most {MAX_TILES} are allowed"
            )
        return self


class ZRangePolicy(_Model):
    """How wide a stack to take: +/- k_sigma predicted sigmas, within [min, max] frames.

    These defaults are the product's (k_sigma tuned in docs/estimators.md): the
    estimator and the scheduler take theirs from here.
    """

    k_sigma: float = Field(2.0, gt=0, le=100)
    z_step_um: float = Field(0.5, ge=1e-3, le=1e3)
    min_frames: int = Field(5, ge=2, le=MAX_FRAMES)
    max_frames: int = Field(41, ge=2, le=MAX_FRAMES)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.min_frames > self.max_frames:
            raise ValueError(
                f"min_frames ({self.min_frames}) must not exceed max_frames ({self.max_frames})"
            )
        return self


class SlideCreate(_Model):
    """A new slide scan: its grid, its strategy and what is known before the first tile."""

    strategy: str = Field(
        min_length=1,
        max_length=64,
        description="A strategy name, as `focustrack bench accuracy` knows it",
        examples=["kf-wiener0"],
    )
    params: dict[Annotated[str, Field(max_length=64)], ParamValue] = Field(
        default_factory=dict,
        max_length=64,
        description="The strategy's parameters by name; omitted ones take their defaults",
    )
    grid: Grid
    # The product's defaults: the estimator and the scheduler take theirs from here.
    start_z_um: Height = 0.0
    start_sigma_um: Sigma = 10.0
    dof_um: Sigma = 1.0
    noise_sigma_um: Sigma = 1.5
    z_range: ZRangePolicy = Field(default_factory=ZRangePolicy)
    label: str | None = Field(None, max_length=200, description="Free text for the lab software")


class Slide(BaseModel):
    """A slide's configuration (with every strategy parameter resolved) and its progress."""

    id: str
    config: SlideCreate
    n_acquisitions: int = Field(description="Measurements recorded so far")
    n_accepted: int = Field(description="Of which were used as observations")
    done: bool = Field(description="True when every tile has been imaged")
    created_unix_s: float
    updated_unix_s: float


class SlideSummary(Slide):
    """A slide as the listing shows it: its configuration without large arrays, and progress."""

    omitted_params: list[str] = Field(
        default_factory=list,
        description=f"Parameters left out of `config.params` for holding more than "
        f"{MAX_LISTED_VALUES} values (a prior map): `GET /v1/slides/{{id}}` has them",
    )


class Next(BaseModel):
    """The next acquisition: a tile, the z-range to acquire there, and why; or `done`."""

    done: bool
    sequence: int | None = Field(None, description="Send it back with the measurement")
    row: int | None = None
    col: int | None = None
    stage_x_um: float | None = None
    stage_y_um: float | None = None
    z_center_um: float | None = None
    z_low_um: float | None = None
    z_high_um: float | None = None
    z_step_um: float | None = None
    n_frames: int | None = None
    predicted_z_um: float | None = Field(None, description="The prior of this tile's focus")
    predicted_sigma_um: float | None = None
    purpose: Purpose | None = None
    measure: bool | None = Field(None, description="False: only image the tile, at z_center_um")


class MeasurementIn(_Model):
    """The best focus found in the stack of acquisition `sequence` at tile (row, col)."""

    row: int = Field(ge=0, le=MAX_GRID_SIDE)
    col: int = Field(ge=0, le=MAX_GRID_SIDE)
    sequence: int = Field(ge=0, le=2**31)
    z_um: Height | None = Field(description="Best focus in um; null when there is none")
    sigma_um: Sigma | None = Field(None, description="Its std; null: the slide's noise sigma")
    flags: list[Flag] = Field(default_factory=list, max_length=len(FocusFlag))
    runner_up_z_um: Height | None = Field(
        None, description="With multi_peak: the next most likely peak's z in um (never taken)"
    )
    chosen_probability: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="With multi_peak: the chance that z_um's peak is the focus",
    )
    frame_out_of_focus: bool = Field(
        False,
        description="Only for an acquisition that images the tile (measure false): its frame "
        "was found out of focus (less sharp than the first pass's image of the tile); the "
        "tile is then measured",
    )

    @model_validator(mode="after")
    def _one_edge(self) -> Self:
        # each says where the next stack goes: both at once is a broken focus reader
        if {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH} <= set(self.flags):
            raise ValueError(
                "flags edge_low and edge_high contradict each other: a peak lies beyond one "
                "end of the stack, not both"
            )
        return self


class OutcomeOut(BaseModel):
    """What the measurement did to its tile's estimate (heights in um)."""

    sequence: int
    row: int
    col: int
    accepted: bool = Field(description="Used as an observation")
    prior_um: float | None
    prior_sigma_um: float | None
    posterior_um: float | None
    posterior_sigma_um: float | None
    innovation_um: float | None
    nis: float | None = Field(description="Normalised innovation squared")
    planes_um: list[float] = Field(
        default_factory=list,
        description="Where the tile's image alone is too unsure (risk_out_of_focus), the "
        "heights of every frame it keeps, ascending, each within a depth of field of the next: "
        "the tile is in focus when one of them is. Empty: keep the frame nearest the posterior",
    )


class FocusMapOut(BaseModel):
    """A slide's focus maps, each rows x cols in um, row-major; null where there is no value."""

    rows: int
    cols: int
    prior_um: list[list[float | None]]
    prior_sigma_um: list[list[float | None]]
    posterior_um: list[list[float | None]]
    posterior_sigma_um: list[list[float | None]]
    z_used_um: list[list[float | None]]
    smoothed_um: list[list[float | None]] | None
    smoothed_sigma_um: list[list[float | None]] | None
    out_of_focus_risk: list[list[float | None]] | None = Field(
        None,
        description="Each tile's predicted probability (0..1) that its kept frame lies outside "
        "the depth of field; null where the strategy states none",
    )


class InnovationStats(BaseModel):
    """Innovation statistics of the accepted measurements, in scan order (thesis section 3-4-3).

    A consistent filter has zero-mean, white innovations whose normalised squares
    (NIS) average to 1: `mean_nis` inside [nis_low, nis_high], `|mean_z|` <= 1.96,
    the Ljung-Box p-value above 0.05.
    """

    n: int
    mean_innovation_um: float
    mean_z: float = Field(description="Mean normalised innovation times sqrt(n); ~N(0, 1)")
    mean_nis: float
    nis_low: float = Field(description="95% interval of mean_nis for a consistent filter")
    nis_high: float
    autocorrelation: list[float] = Field(description="Of normalised innovations, lags 0..max_lag")
    autocorrelation_bound: float = Field(description="95% band of a white sequence, +/-")
    ljung_box_q: float
    ljung_box_p: float
    zero_mean: bool
    consistent: bool
    white: bool


class RiskStats(BaseModel):
    """The imaged tiles' predicted out-of-focus risk against the slide's stated one.

    Each tile's risk is the filter's probability that its kept frame lies outside the
    depth of field (the map's `out_of_focus_risk`); their mean is the share of tiles
    expected out of focus.
    """

    stated_risk: float | None = Field(
        description="The slide's risk_out_of_focus; null where the strategy states none"
    )
    n_tiles: int = Field(description="Imaged tiles with a predicted risk")
    expected_out_of_focus: float = Field(description="Mean predicted risk of those tiles")
    n_over_stated: int = Field(description="Tiles whose predicted risk exceeds the stated one")
    note: str | None = Field(description="Why the stated risk is not met, when it is not")


class Diagnostics(BaseModel):
    n_acquisitions: int
    n_measured: int = Field(description="Acquisitions that asked for a best focus")
    n_accepted: int = Field(description="Measurements used as observations")
    n_rejected: int = Field(description="Measured but not used: edge peak, flat curve, gated out")
    innovations: InnovationStats | None
    innovations_note: str | None = Field(description="Why there are no innovation statistics")
    risk: RiskStats | None = Field(
        None, description="Predicted out-of-focus risk; null before a tile with one is imaged"
    )
    sigma_scale: float = Field(
        1.0,
        description="The slide's factor on the focus service's sigmas, learnt from the "
        "innovations (1 until they show the sigmas too small; at most 5)",
    )


class StrategyInfo(BaseModel):
    """A served strategy and its parameters (`GET /v1/strategies`)."""

    name: str = Field(description="The strategy's name, as `SlideCreate.strategy` takes it")
    parameters: dict[str, Any] = Field(
        description="The JSON schema of its parameters: each one's type, default, unit (in "
        "its name or its description) and bounds"
    )
    defaults: dict[str, Any] = Field(
        description="Every parameter at its default: a slide created without `params` has these"
    )


class Health(BaseModel):
    status: str = Field(description="`ok`, or `degraded` while the store is (see `problem`)")
    slides: int | None = Field(description="Slides in the store; None while it cannot be read")
    problem: str | None = Field(None, description="Why the store is degraded")


class ErrorCode(StrEnum):
    """What went wrong, for programs (the HTTP status says it coarsely, `detail` for people)."""

    INVALID_REQUEST = "invalid_request"  # 422: malformed or refused input
    UNAUTHORIZED = "unauthorized"  # 401: no or a wrong bearer token
    NOT_FOUND = "not_found"  # 404: no such slide (or route)
    METHOD_NOT_ALLOWED = "method_not_allowed"  # 405: the route takes other methods (`Allow`)
    CONFLICT = "conflict"  # 409: contradicts the slide's state
    SLIDE_LOG_CORRUPT = "slide_log_corrupt"  # 409: the slide's stored log fails its checks
    STRATEGY_NOT_SERVED = "strategy_not_served"  # 409: the service does not serve its strategy
    PAYLOAD_TOO_LARGE = "payload_too_large"  # 413: the body is over the limit
    REPLAY_MISMATCH = "replay_mismatch"  # 500: the stored log no longer replays
    INTERNAL = "internal"  # 500: the service failed
    STORAGE_FULL = "storage_full"  # 507: the estimator's disk is full; ask again later


class Error(BaseModel):
    """Every error reply: a `code` to branch on and a `detail` to show."""

    code: ErrorCode
    detail: str | list[dict[str, object]] = Field(
        description="A message, or validation errors each with `loc`, `msg` and `type`"
    )
