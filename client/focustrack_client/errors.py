"""Errors of the estimator's REST API as exception types, chosen by the reply's `code`.

Every error reply carries `{"code": ..., "detail": ...}`; `detail` is for people
(a message, or a list of validation errors with their `loc`), `code` is for
programs. Decide on the type (or on `.code`), never on the message text.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import httpx

from typing import Any

from focustrack_client.models import ErrorCode


class EstimatorError(Exception):
    """An error reply of the estimator: `status` (HTTP), `code` and `detail`."""

    def __init__(self, status: int, code: ErrorCode, detail: Any) -> None:
        super().__init__(f"{status} {code}: {detail}")
        self.status, self.code, self.detail = status, code, detail


class InvalidRequestError(EstimatorError):
    """422: the request is malformed or refused (`detail` says which field and why)."""


class UnauthorizedError(EstimatorError):
    """401: no or a wrong bearer token."""


class SlideNotFoundError(EstimatorError):
    """404: no slide of that id (or no such route)."""


class ConflictError(EstimatorError):
    """409: the request contradicts the slide's state (not the pending acquisition, ...)."""


class SlideLogCorruptError(ConflictError):
    """409 `slide_log_corrupt`: the slide's stored log fails its own checks; that slide
    stops (asking again will not help) while the others are served."""


class StrategyNotServedError(ConflictError):
    """409 `strategy_not_served`: the slide's strategy is not among those the service was
    started to serve (`--strategies-from`); that slide waits for a service that does."""


class PayloadTooLargeError(EstimatorError):
    """413: the request body is over the service's limit."""


class ServerError(EstimatorError):
    """5xx: the service failed; the request may be retried."""


class StorageFullError(ServerError):
    """507: the estimator's disk is full; nothing was written, ask again after Retry-After."""


_BY_CODE: dict[ErrorCode, type[EstimatorError]] = {
    ErrorCode.INVALID_REQUEST: InvalidRequestError,
    ErrorCode.UNAUTHORIZED: UnauthorizedError,
    ErrorCode.NOT_FOUND: SlideNotFoundError,
    ErrorCode.METHOD_NOT_ALLOWED: InvalidRequestError,
    ErrorCode.CONFLICT: ConflictError,
    ErrorCode.SLIDE_LOG_CORRUPT: SlideLogCorruptError,
    ErrorCode.STRATEGY_NOT_SERVED: StrategyNotServedError,
    ErrorCode.PAYLOAD_TOO_LARGE: PayloadTooLargeError,
    ErrorCode.REPLAY_MISMATCH: ServerError,
    ErrorCode.INTERNAL: ServerError,
    ErrorCode.STORAGE_FULL: StorageFullError,
}


def raise_for_error(response: httpx.Response) -> None:
    """Raise the `EstimatorError` of an error reply; return for a success."""
    if response.is_success:
        return
    try:
        body = response.json()
    except ValueError:
        body = {}
    body = body if isinstance(body, dict) else {}
    try:
        code = ErrorCode(str(body.get("code")))
    except ValueError:
        code = ErrorCode.INTERNAL if response.is_server_error else ErrorCode.INVALID_REQUEST
    raise _BY_CODE[code](response.status_code, code, body.get("detail", response.text))
