"""What the routes depend on: the live slides, the metrics, the bearer token, a slide's id.

Dependencies are coroutines: FastAPI runs plain functions in its thread pool, a
thread hop per dependency per request (it tripled the latency of /next).
"""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from focustrack_estimator.metrics import EstimatorMetrics
from focustrack_estimator.slides import Slides

SlideId = Annotated[str, Path(min_length=1, max_length=64, description="The id POST returned")]

_bearer = HTTPBearer(auto_error=False, description="Required when the service has a token")


async def require_token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """A 401 unless the request carries the service's bearer token (its settings')."""
    token: str = request.app.state.settings.token
    if credentials is None or not secrets.compare_digest(
        credentials.credentials.encode(), token.encode()
    ):
        raise HTTPException(
            401, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"}
        )


async def _slides(request: Request) -> Slides:
    return request.app.state.slides


async def _metrics(request: Request) -> EstimatorMetrics:
    return request.app.state.metrics


SlidesDep = Annotated[Slides, Depends(_slides)]
MetricsDep = Annotated[EstimatorMetrics, Depends(_metrics)]
