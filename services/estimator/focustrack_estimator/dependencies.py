"""What the routes depend on: the live slides, the metrics, a slide's id.

Dependencies are coroutines: FastAPI runs plain functions in its thread pool, a
thread hop per dependency per request (it tripled the latency of /next).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, HTTPException, Path, Request

from focustrack_client import models as api
from focustrack_estimator.metrics import EstimatorMetrics
from focustrack_estimator.slides import Slides

SlideId = Annotated[str, Path(min_length=1, max_length=64, description="The id POST returned")]


def media_type(request: Request) -> str:
    """The request's media type, lower case, without its parameters ('' if it has none)."""
    return request.headers.get("content-type", "").partition(";")[0].strip().lower()


async def json_body(request: Request) -> None:
    """A 415 for a body sent as anything but JSON (FastAPI reads no other media type, nor a
    body without one, as JSON): curl's ``-d`` sends a form's media type unless told
    otherwise, and FastAPI would then say only that the body is no object."""
    media = media_type(request)
    if media != "application/json" and not media.endswith("+json"):
        raise HTTPException(
            415,
            f"the body is JSON, sent as application/json; got {media or 'no Content-Type'} "
            "(curl: -H 'Content-Type: application/json')",
        )


#: The 415 of a route whose body is JSON (OpenAPI).
JSON_BODY_RESPONSES: dict[int | str, dict[str, Any]] = {
    415: {"model": api.Error, "description": "The body not sent as application/json"}
}


async def _slides(request: Request) -> Slides:
    return request.app.state.slides


async def _metrics(request: Request) -> EstimatorMetrics:
    return request.app.state.metrics


SlidesDep = Annotated[Slides, Depends(_slides)]
MetricsDep = Annotated[EstimatorMetrics, Depends(_metrics)]
