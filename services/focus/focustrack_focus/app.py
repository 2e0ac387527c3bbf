"""The focus service over REST (FastAPI): a z-stack or a focus curve in, a focus result out.

- ``POST /v1/focus/stack``: multipart, ``stack`` (a multi-page TIFF or a .npy
  array, frames first: (n, H, W) or (n, H, W, C)) and ``z_um`` (the z of each
  frame in um: a JSON list or comma-separated numbers); optional ``metric``,
  ``mode``, ``channel``, ``lowpass_sigma_px``.
- ``POST /v1/focus/curve``: JSON ``{"z_um": [...], "scores": [...]}`` (optional
  ``metric`` label, which picks the metric's entry of the service's microscope
  profile where it has one, else `unprofiled` where it is none of the service's metrics,
  ``mode`` and ``prior``: ``{"z_um": m, "sigma_um": s}``, the
  estimator's belief before this stack), for lab software that computes its own
  scores. ``best_z_um``/``sigma_um`` are always the curve's own measurement; with
  a prior the reply adds ``posterior_z_um``/``posterior_sigma_um`` (both combined).
- ``GET /healthz``. OpenAPI docs at ``/docs``.

Bad input is a 4xx whose detail names the problem: 413 for an oversized body
(or a stack that would decode to more than the limit), 415 for a file that is
neither TIFF nor .npy or a body that is no form, 408 for a body that arrives too
slowly, 401 without the token (when one is set), 422 for the rest. What a request may
ask is bounded (`FocusLimits`): bytes, decoded pixels (checked from the file's header,
before decoding), frames, JSON size and nesting.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from typing import Annotated, Any

import numpy as np
from fastapi import Depends, FastAPI, File, Form, HTTPException, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from focustrack_core.domain import MAX_ABS_Z_UM, MAX_PRIOR_SIGMA_UM, MIN_PRIOR_SIGMA_UM, Prior
from focustrack_core.http_metrics import HttpMetrics
from focustrack_core.stacks import (
    TooLargeError,
    UnsupportedFileError,
    decode_stack,
    parse_z_list,
)
from focustrack_core.web import (
    bearer_scheme,
    check_least,
    form_as_declared,
    guarded_app,
    read_upload,
)
from focustrack_focus.metrics import DEFAULT_METRIC, METRICS
from focustrack_focus.peak import MIN_CURVE_FRAMES, PeakMode
from focustrack_focus.pipeline import (
    STACK_LAYOUT,
    FocusSettings,
    focus_from_curve,
    focus_stack,
)
from focustrack_focus.preprocess import MAX_LOWPASS_SIGMA_PX
from focustrack_focus.profile import MAX_METRIC_NAME_CHARS, MicroscopeProfile

#: The route of a stack's upload, the one whose requests `FocusLimits.max_concurrent` counts.
STACK_PATH = "/v1/focus/stack"
#: The least each limit of `FocusLimits` may be: below, a limit admits no request (a
#: stack of one frame with its form; a curve's JSON object of two lists), or, for frames,
#: no curve or stack with a peak to find (a look of one frame alone).
LEAST_LIMITS = {
    "max_upload_bytes": 4096,
    "max_decoded_bytes": 1,
    "max_frames": MIN_CURVE_FRAMES,
    "max_json_bytes": 32,
    "max_json_depth": 2,
    "max_concurrent": 1,
}


@dataclass(frozen=True)
class FocusLimits:
    """What one request may ask of the service (its settings; each a flag of the command).

    max_upload_bytes: the whole request body (a stack of 21 frames of 2048x2048
    uint16 is 176 MB); max_decoded_bytes: the pixels a stack decodes to, read from
    its header before decoding (a 3.5 MB zlib TIFF can hold 3.6 GB); max_frames: of
    a stack or curve; max_json_bytes and max_json_depth: a curve's JSON body and
    how deeply it may nest; body_timeout_s: how long a body may take to arrive;
    max_concurrent: the stacks read at once (one more is a 503, before its body is read):
    each may hold its upload and its decoded frames, so these bound the service's memory
    (curves, of 1 MB at most, are not counted).
    """

    max_upload_bytes: int = 256 << 20
    max_decoded_bytes: int = 512 << 20
    max_frames: int = 1001
    max_json_bytes: int = 1 << 20
    max_json_depth: int = 32
    body_timeout_s: float = 60.0
    max_concurrent: int = 2

    def __post_init__(self) -> None:
        check_least(self, LEAST_LIMITS)
        if not self.body_timeout_s > 0:
            raise ValueError(f"the body timeout must be positive, got {self.body_timeout_s} s")


#: A number of a curve's JSON: a finite JSON number, integer or not; never true or "1"
#: (pydantic's lax mode reads those as 1.0).
Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]


class PriorModel(BaseModel):
    """The estimator's belief about the focus before this stack (um)."""

    model_config = ConfigDict(extra="forbid")

    # the bounds `Prior` computes within (`domain.MIN_PRIOR_SIGMA_UM` says why)
    z_um: Annotated[Number, Field(ge=-MAX_ABS_Z_UM, le=MAX_ABS_Z_UM)]
    sigma_um: Annotated[Number, Field(ge=MIN_PRIOR_SIGMA_UM, le=MAX_PRIOR_SIGMA_UM)]


class CurveRequest(BaseModel):
    """A focus curve: the z (um) of each frame and its score."""

    model_config = ConfigDict(extra="forbid")

    z_um: list[Number] = Field(min_length=MIN_CURVE_FRAMES)
    scores: list[Number] = Field(min_length=MIN_CURVE_FRAMES)
    metric: str = Field(
        DEFAULT_METRIC,
        min_length=1,
        max_length=MAX_METRIC_NAME_CHARS,
        description="label of the metric that made the scores (picks its profile entry)",
    )
    mode: PeakMode = PeakMode.MAX
    prior: PriorModel | None = Field(
        None, description="the estimator's prior; weighs peaks, adds the posterior"
    )

    @model_validator(mode="after")
    def _same_length(self) -> CurveRequest:
        if len(self.z_um) != len(self.scores):
            raise ValueError(
                f"{len(self.z_um)} z values but {len(self.scores)} scores: one score per z needed"
            )
        return self


class FocusResponse(BaseModel):
    """The focus of a stack or curve (the JSON of `FocusResult`)."""

    z_um: list[float]
    scores: list[float]
    best_z_um: float | None
    sigma_um: float | None
    flags: list[str]
    metric: str
    compute_time_s: float
    runner_up_z_um: float | None = Field(None, description="z of the next most likely peak")
    chosen_probability: float | None = Field(
        None, description="probability that best_z_um's peak is the focus (peak choice)"
    )
    posterior_z_um: float | None = Field(None, description="prior and measurement combined")
    posterior_sigma_um: float | None = None


class ErrorReply(BaseModel):
    """A refusal (4xx): what is wrong."""

    detail: str | list[dict[str, Any]] = Field(
        description="a sentence naming the problem, or each invalid field with its location"
    )


def curve_schemas() -> dict[str, Any]:
    """The OpenAPI components of `CurveRequest`: its schema and those it refers to (as
    ``#/components/schemas/...``), for the document's components; FastAPI does not see the
    body, which `focus_curve` reads by hand."""
    schema = CurveRequest.model_json_schema(ref_template="#/components/schemas/{model}")
    return {**schema.pop("$defs", {}), CurveRequest.__name__: schema}


class RepeatedKeyError(ValueError):
    """A JSON object gives a key twice (`members_once`)."""


def members_once(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's members as a dict (json's `object_pairs_hook`); RepeatedKeyError
    naming a key given twice, of which json would keep the last, silently."""
    members: dict[str, Any] = {}
    for key, value in pairs:
        if key in members:
            raise RepeatedKeyError(f"JSON key {key!r} given more than once; send each key once")
        members[key] = value
    return members


def json_depth_exceeds(text: bytes, max_depth: int) -> bool:
    """Whether JSON `text` nests arrays or objects deeper than `max_depth` (brackets in
    strings aside); checked before parsing, which would recurse that deep."""
    depth, in_string, escaped = 0, False, False
    for byte in text:
        if in_string:
            if escaped:
                escaped = False
            elif byte == 0x5C:  # backslash
                escaped = True
            elif byte == 0x22:  # quote
                in_string = False
        elif byte == 0x22:
            in_string = True
        elif byte in (0x5B, 0x7B):  # [ {
            depth += 1
            if depth > max_depth:
                return True
        elif byte in (0x5D, 0x7D):  # ] }
            depth -= 1
    return False


def create_app(
    settings: FocusSettings | None = None,
    limits: FocusLimits | None = None,
    token: str | None = None,
    profile: MicroscopeProfile | None = None,
) -> FastAPI:
    """The REST app; `settings` are the defaults that request fields override, `limits`
    what one request may ask, `token` the bearer token /v1 requires (None: open);
    `profile`: the microscope's constants per metric, picked by a request's metric."""
    base = settings or FocusSettings()
    limits = limits or FocusLimits()
    profile = profile or MicroscopeProfile({})

    token_scheme = bearer_scheme(token)
    app = guarded_app(
        "focustrack focus service",
        "Best focus (with an uncertainty and flags) from a z-stack or a focus curve.",
        limits.max_upload_bytes,
        limits.body_timeout_s,
        HttpMetrics("focustrack_focus"),
        token,
        limits.max_concurrent,
        bounded_prefix=STACK_PATH,
    )

    def refusals(statuses: dict[int, str]) -> dict[int | str, dict[str, Any]]:
        """A /v1 route's OpenAPI `responses` besides its 200: `statuses` (status -> when it
        is answered), the 408 of a slow body, and the 401 without the token where one is set."""
        every = {408: f"the body did not arrive within {limits.body_timeout_s:g} s"}
        if token is not None:
            every[401] = "without the bearer token"
        return {
            status: {"model": ErrorReply, "description": text}
            for status, text in sorted((every | statuses).items())
        }

    max_body = limits.max_upload_bytes  # of every route (`guarded_app`)

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return {"status": "ok", "metrics": list(METRICS), "default_metric": base.metric}

    @app.post(
        "/v1/focus/curve",
        response_model=FocusResponse,
        dependencies=[Depends(token_scheme)],
        responses=refusals(
            {
                413: f"the body is over {min(limits.max_json_bytes, max_body)} bytes",
                422: "not JSON, a key given twice, a field missing, unknown or invalid, or a "
                "curve the maths refuses: the detail names the problem",
            }
        ),
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {
                    "application/json": {
                        "schema": {"$ref": f"#/components/schemas/{CurveRequest.__name__}"}
                    }
                },
            }
        },
    )
    async def focus_curve(http: Request) -> dict[str, Any]:
        # The body is read and checked here, not by FastAPI: its size and nesting are
        # bounded before it is parsed (a 59 MB body, 100 000 nested lists).
        body = b""
        async for chunk in http.stream():
            body += chunk
            if len(body) > limits.max_json_bytes:
                raise HTTPException(
                    413, f"the curve's JSON exceeds the limit of {limits.max_json_bytes} bytes"
                )
        if json_depth_exceeds(body, limits.max_json_depth):
            raise HTTPException(422, f"the JSON nests deeper than {limits.max_json_depth} levels")
        try:
            # Every number of a curve is a float: integers read as floats, so one of 400 or
            # 5000 digits is an infinite number (a 422 saying so), not "Input should be a
            # valid number" or Python's advice on sys.set_int_max_str_digits.
            document = json.loads(body, object_pairs_hook=members_once, parse_int=float)
        except RepeatedKeyError as error:
            raise HTTPException(422, str(error)) from None
        except ValueError as error:  # json's errors, and bytes that are not UTF-8
            raise HTTPException(422, f"the body is not JSON: {error}") from None
        try:
            request = CurveRequest.model_validate(document)
        except ValidationError as error:
            errors = [{**item, "loc": ("body", *item["loc"])} for item in error.errors()]
            raise RequestValidationError(errors) from None
        if len(request.z_um) > limits.max_frames:
            raise HTTPException(
                422, f"the curve has {len(request.z_um)} points; the limit is {limits.max_frames}"
            )
        return await run_in_threadpool(_curve, request)

    def _curve(request: CurveRequest) -> dict[str, Any]:
        for_metric = profile.settings_for(request.metric, base)
        chosen = replace(for_metric, peak=replace(for_metric.peak, mode=request.mode))
        try:
            prior = (
                None if request.prior is None else Prior(request.prior.z_um, request.prior.sigma_um)
            )
            result = focus_from_curve(
                np.array(request.z_um), np.array(request.scores), chosen, prior=prior
            )
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
        return result.to_json() | {"metric": request.metric}

    @app.post(
        STACK_PATH,
        response_model=FocusResponse,
        dependencies=[Depends(token_scheme), Depends(form_as_declared)],
        responses=refusals(
            {
                413: f"the body is over {max_body} bytes, or the stack would "
                f"decode to over {limits.max_decoded_bytes} bytes",
                415: "the stack is neither a TIFF nor a .npy file, or the body is no form",
                503: f"{limits.max_concurrent} stacks are being read already: ask again after "
                "the Retry-After header's seconds",
                422: "a form field missing, unknown, given twice or invalid, or a stack the "
                "maths refuses: the detail names the problem",
            }
        ),
    )
    async def focus_stack_endpoint(
        stack: Annotated[UploadFile, File(description="multi-page TIFF or .npy, frames first")],
        z_um: Annotated[str, Form(description="z of each frame, um: JSON list or a,b,c")],
        metric: Annotated[str, Form()] = base.metric,
        mode: Annotated[PeakMode, Form()] = base.peak.mode,
        channel: Annotated[int | None, Form(ge=0)] = base.preprocess.channel,
        lowpass_sigma_px: Annotated[
            float, Form(ge=0, le=MAX_LOWPASS_SIGMA_PX, allow_inf_nan=False)
        ] = base.preprocess.lowpass_sigma_px,
    ) -> dict[str, Any]:
        data = await read_upload(stack, limits.max_upload_bytes)
        try:
            z = parse_z_list(z_um)
            if metric not in METRICS:
                raise ValueError(f"unknown focus metric {metric!r}; known: {', '.join(METRICS)}")
            chosen = FocusSettings(
                preprocess=replace(
                    base.preprocess, channel=channel, lowpass_sigma_px=lowpass_sigma_px
                ),
                metric=metric,
                peak=replace(profile.settings_for(metric, base).peak, mode=mode),
            )
            frames = await run_in_threadpool(
                decode_stack, data, limits.max_frames, limits.max_decoded_bytes
            )
            if frames.ndim == 2:  # a .npy of one frame (a TIFF's page is a frame of its own)
                raise ValueError(
                    f"the .npy is a single {frames.shape} frame: {STACK_LAYOUT}; "
                    "send one frame (a look) as (1, H, W)"
                )
            result = await run_in_threadpool(focus_stack, frames, z, chosen)
        except UnsupportedFileError as error:
            raise HTTPException(415, str(error)) from None
        except TooLargeError as error:
            raise HTTPException(413, str(error)) from None
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
        return result.to_json()

    build_openapi = app.openapi  # FastAPI's: built once, then kept
    schemas = curve_schemas()

    def openapi() -> dict[str, Any]:
        document = build_openapi()
        document.setdefault("components", {}).setdefault("schemas", {}).update(schemas)
        return document

    app.openapi = openapi  # type: ignore[method-assign]
    return app
