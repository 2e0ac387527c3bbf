"""A slim client of FocusTrack's estimator REST API for lab software (httpx, pydantic and the
OpenTelemetry API only: the caller's trace context goes with each request).

`EstimatorClient` (blocking) and `AsyncEstimatorClient` return the typed models of
`focustrack_client.models`, which the estimator service itself validates with;
error replies raise the types of `focustrack_client.errors`.

The names below are imported on first use (PEP 562), so that a program that needs
only the models (the estimator service itself) does not import httpx.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from focustrack_client.client import AsyncEstimatorClient, EstimatorClient, SlidePage
    from focustrack_client.errors import (
        ConflictError,
        EstimatorError,
        InvalidRequestError,
        PayloadTooLargeError,
        ServerError,
        SlideLogCorruptError,
        SlideNotFoundError,
        StorageFullError,
        StrategyNotServedError,
        UnauthorizedError,
    )
    from focustrack_client.models import Grid, MeasurementIn, SlideCreate, ZRangePolicy

#: Each public name and the module that defines it.
_HOMES = {
    "AsyncEstimatorClient": "client",
    "EstimatorClient": "client",
    "SlidePage": "client",
    "ConflictError": "errors",
    "EstimatorError": "errors",
    "InvalidRequestError": "errors",
    "PayloadTooLargeError": "errors",
    "ServerError": "errors",
    "SlideLogCorruptError": "errors",
    "SlideNotFoundError": "errors",
    "StorageFullError": "errors",
    "StrategyNotServedError": "errors",
    "UnauthorizedError": "errors",
    "Grid": "models",
    "MeasurementIn": "models",
    "SlideCreate": "models",
    "ZRangePolicy": "models",
}

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
    "SlideLogCorruptError",
    "SlideNotFoundError",
    "SlidePage",
    "StorageFullError",
    "StrategyNotServedError",
    "UnauthorizedError",
    "ZRangePolicy",
]


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"focustrack_client.{_HOMES[name]}"), name)
