"""A slim client of FocusTrack's estimator REST API for lab software (httpx and pydantic only).

`EstimatorClient` (blocking) and `AsyncEstimatorClient` return the typed models of
`focustrack_client.models`, which the estimator service itself validates with;
error replies raise the types of `focustrack_client.errors`.
"""

from focustrack_client.client import AsyncEstimatorClient, EstimatorClient
from focustrack_client.errors import (
    ConflictError,
    EstimatorError,
    InvalidRequestError,
    PayloadTooLargeError,
    ServerError,
    SlideNotFoundError,
    UnauthorizedError,
)
from focustrack_client.models import Grid, MeasurementIn, SlideCreate, ZRangePolicy

__all__ = [
    "AsyncEstimatorClient",
    "ConflictError",
    "EstimatorClient",
    "EstimatorError",
    "Grid",
    "InvalidRequestError",
    "MeasurementIn",
    "PayloadTooLargeError",
    "ServerError",
    "SlideCreate",
    "SlideNotFoundError",
    "UnauthorizedError",
    "ZRangePolicy",
]
