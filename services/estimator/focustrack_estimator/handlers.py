"""The REST API's errors: each domain error's HTTP status and code, and the one reply shape.

Every error reply is an `api.Error`: a `code` for programs and a `detail` naming
the problem, quoting at most 200 characters of any input (404 unknown slide, 409
not the pending acquisition or a conflicting re-post, 409 `slide_log_corrupt` a slide
whose stored log fails its own checks, 422 invalid input or a slide over the cost
budget, 413 oversized body, 408 a body too slow to arrive, 503 a store that failed
under the request, 507 `storage_full` a full disk, 500 a log that no longer replays
or an unexpected failure). A 422 from the domain has the shape of FastAPI's own.
"""

from __future__ import annotations

import errno
import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import Scope

from focustrack_client import models as api
from focustrack_core.serving import MAX_MESSAGE_CHARS, cut
from focustrack_estimator.errors import (
    ReplayMismatchError,
    SlideConflictError,
    SlideError,
    SlideNotFoundError,
    StrategyNotServedError,
)
from focustrack_estimator.event_store import (
    CorruptLogError,
    StoreFullError,
    StoreUnavailableError,
)

log = logging.getLogger(__name__)

#: Seconds a client is told to wait before it asks again after a 503 or a 507.
RETRY_AFTER_UNAVAILABLE_S = 5
RETRY_AFTER_FULL_S = 30

#: The status and code of each domain error (a subclass takes its nearest ancestor's).
DOMAIN_ERRORS: dict[type[SlideError], tuple[int, api.ErrorCode]] = {
    SlideError: (422, api.ErrorCode.INVALID_REQUEST),
    SlideNotFoundError: (404, api.ErrorCode.NOT_FOUND),
    SlideConflictError: (409, api.ErrorCode.CONFLICT),
    StrategyNotServedError: (409, api.ErrorCode.STRATEGY_NOT_SERVED),
    ReplayMismatchError: (500, api.ErrorCode.REPLAY_MISMATCH),
}

#: The error replies every /v1 operation documents (in the OpenAPI schema).
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": api.Error, "description": text}
    for status, text in (
        (401, "Missing or wrong bearer token"),
        (404, "Unknown slide"),
        (
            409,
            "Not the pending acquisition, a conflicting re-post, a finished scan, or a slide "
            "whose stored log is corrupt (`slide_log_corrupt`)",
        ),
        (413, "Request body too large"),
        (503, "The store failed under the request (nothing was done); ask again later"),
        (507, "The store's disk is full (nothing was done); ask again after Retry-After s"),
    )
}

#: The error code of an HTTP status the service answers without a more specific one.
_CODE_OF_STATUS = {
    401: api.ErrorCode.UNAUTHORIZED,
    404: api.ErrorCode.NOT_FOUND,
    405: api.ErrorCode.METHOD_NOT_ALLOWED,
    409: api.ErrorCode.CONFLICT,
    413: api.ErrorCode.PAYLOAD_TOO_LARGE,
    422: api.ErrorCode.INVALID_REQUEST,
}


def error_response(
    status: int,
    code: api.ErrorCode | None,
    detail: object,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    """An error reply in the one shape of `api.Error`: a `code` for programs, a `detail`
    (long inputs quoted in it are cut: `focustrack_core.serving.cut`)."""
    if code is None:
        default = api.ErrorCode.INTERNAL if status >= 500 else api.ErrorCode.INVALID_REQUEST
        code = _CODE_OF_STATUS.get(status, default)
    return JSONResponse({"code": code, "detail": _cut_quotes(detail)}, status, headers=headers)


def _cut_quotes(detail: object) -> object:
    """`detail` with its messages cut at `MAX_MESSAGE_CHARS` and the parts of its locations
    (a key of the input, which may be 1 MB) at `MAX_QUOTED_CHARS`."""
    if isinstance(detail, str):
        return cut(detail, MAX_MESSAGE_CHARS)
    if isinstance(detail, list | tuple):
        return [_cut_quotes(item) for item in detail]
    if isinstance(detail, dict):
        return {
            key: [cut(part) if isinstance(part, str) else part for part in value]
            if key == "loc" and isinstance(value, list | tuple)
            else _cut_quotes(value)
            for key, value in detail.items()
        }
    return detail


#: How pydantic names the members of `api.ParamValue` in the locations of its errors.
_PARAM_VALUE_MEMBERS = frozenset({"bool", "int", "float", "str", "list[float]"})


def _one_per_parameter(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """`errors` with those of a strategy parameter that fits no member of `api.ParamValue`
    (one per member, located at ``params.q.bool``, ``params.q.int``, ...) made one, at the
    parameter: a NaN is not a finite number; an item of a list, not a number; else what
    a parameter may be."""
    kept: list[dict[str, Any]] = []
    by_parameter: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for item in errors:
        loc = tuple(item["loc"])
        if loc[:2] == ("body", "params") and len(loc) > 3 and loc[3] in _PARAM_VALUE_MEMBERS:
            by_parameter.setdefault(loc[:3], []).append(item)
        else:
            kept.append(item)
    for where, members in by_parameter.items():
        finite = [m for m in members if m["type"] == "finite_number"]
        items = [m for m in members if len(m["loc"]) > 4]  # a list's item
        if finite or items:
            chosen = (finite or items)[0]
            kept.append({**chosen, "loc": [*where, *chosen["loc"][4:]]})
        else:
            message = "Input should be a number, a boolean, a string, a list of numbers or null"
            kept.append({"loc": list(where), "msg": message, "type": "value_error"})
    return kept


def _storage_full(detail: str) -> JSONResponse:
    """The reply to a write refused for lack of disk space: nothing of it was kept, and the
    same request may succeed once there is space again."""
    retry = {"Retry-After": str(RETRY_AFTER_FULL_S)}
    return error_response(507, api.ErrorCode.STORAGE_FULL, f"{detail}; nothing was written", retry)


def status_of(error: SlideError) -> tuple[int, api.ErrorCode]:
    """The HTTP status and error code of a domain error."""
    kind = next(kind for kind in type(error).__mro__ if kind in DOMAIN_ERRORS)
    return DOMAIN_ERRORS[kind]


#: The methods a path may take, for the `Allow` header of a 405.
_HTTP_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def _allowed_methods(app: FastAPI, scope: Scope) -> list[str]:
    """Every method some route of the app serves at the request's path.

    Each method is tried on the routes' own matching: since FastAPI 0.165 an included
    router is one route of the app, not its routes, and a route's `methods` hide there.
    """
    return [
        method
        for method in _HTTP_METHODS
        if any(route.matches({**scope, "method": method})[0] is Match.FULL for route in app.routes)
    ]


def install(app: FastAPI) -> None:
    """Answer the domain's errors, HTTP errors and invalid requests as `api.Error` replies."""

    @app.exception_handler(SlideError)
    async def slide_error(_: Request, error: SlideError) -> JSONResponse:
        status, code = status_of(error)
        if status == 422:  # the shape of FastAPI's own 422: one schema for clients
            detail = [{"loc": list(error.where), "msg": str(error), "type": "value_error"}]
            return error_response(status, code, detail)
        return error_response(status, code, str(error))

    @app.exception_handler(StoreUnavailableError)
    async def store_unavailable(_: Request, error: StoreUnavailableError) -> JSONResponse:
        # The database failed under the request (I/O, a full disk, a lock): nothing it asked
        # was done; the client may ask again later.
        if isinstance(error, StoreFullError):
            return _storage_full(str(error))
        detail = f"the estimator's store failed: {error}"
        retry = {"Retry-After": str(RETRY_AFTER_UNAVAILABLE_S)}
        return error_response(503, api.ErrorCode.INTERNAL, detail, retry)

    @app.exception_handler(CorruptLogError)
    async def corrupt_log(_: Request, error: CorruptLogError) -> JSONResponse:
        # That slide alone stops: asking again will not help until its log is repaired.
        log.error("%s", error)
        return error_response(
            409, api.ErrorCode.SLIDE_LOG_CORRUPT, f"{error}; the other slides are served"
        )

    @app.exception_handler(OSError)
    async def os_error(_: Request, error: OSError) -> JSONResponse:
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            return _storage_full(f"the estimator's disk is full: {error}")
        log.error("request failed: %r", error)
        return error_response(500, api.ErrorCode.INTERNAL, f"the estimator failed: {error}")

    @app.exception_handler(Exception)
    async def unexpected(_: Request, error: Exception) -> JSONResponse:
        # Starlette still logs the traceback; the client gets the API's shape, not bare text.
        return error_response(500, api.ErrorCode.INTERNAL, f"the estimator failed: {error!r}")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, error: StarletteHTTPException) -> JSONResponse:
        headers = dict(error.headers or {})
        if error.status_code == 405:  # Starlette names the methods of one route; a path has more
            headers["Allow"] = ", ".join(_allowed_methods(app, request.scope))
        if error.status_code == 400:
            # FastAPI's answer to a body it cannot decode (not UTF-8): malformed input like
            # any other, so the documented 422 invalid_request rather than an undocumented 400
            detail = [{"loc": ["body"], "msg": error.detail, "type": "json_invalid"}]
            return error_response(422, api.ErrorCode.INVALID_REQUEST, detail, headers)
        return error_response(error.status_code, None, error.detail, headers)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, error: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes the input, which fails to render when it is NaN or
        # infinite (a 500 for the very values it rejects): say where and what, not the value.
        detail = _one_per_parameter(
            [{"loc": e["loc"], "msg": e["msg"], "type": e["type"]} for e in error.errors()]
        )
        return error_response(422, api.ErrorCode.INVALID_REQUEST, detail)
