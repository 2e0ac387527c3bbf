"""The errors of the estimator's domain: requests it refuses, and logs that no longer replay."""

from __future__ import annotations

from focustrack_client import models as api


class SlideError(Exception):
    """A request the domain refuses; `status` is the HTTP status that says why.

    `where` locates the offending input, as a validation error's `loc` does
    (("body", "params", "q")): a 422 from the domain reads like one from the schema.
    """

    status = 422
    code = api.ErrorCode.INVALID_REQUEST

    def __init__(self, message: str, where: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.where = where


class SlideNotFoundError(SlideError):
    status = 404
    code = api.ErrorCode.NOT_FOUND


class SlideConflictError(SlideError):
    """The request contradicts the slide's state (not the pending acquisition, a re-post
    with a different value, a finished scan)."""

    status = 409
    code = api.ErrorCode.CONFLICT


class ReplayMismatchError(SlideError):
    """The stored log no longer replays to the logged outcomes (the strategy changed)."""

    status = 500
    code = api.ErrorCode.REPLAY_MISMATCH
