"""Error replies become exception types by their code, whatever the message says."""

from __future__ import annotations

import httpx
import pytest

from focustrack_client import (
    ConflictError,
    EstimatorClient,
    EstimatorError,
    InvalidRequestError,
    ServerError,
    SlideLogCorruptError,
    SlideNotFoundError,
    StorageFullError,
    UnauthorizedError,
)
from focustrack_client.models import ErrorCode


def client_answering(status: int, body: object) -> EstimatorClient:
    """A client whose every request gets `status` with JSON `body` (no network)."""
    transport = httpx.MockTransport(lambda _: httpx.Response(status, json=body))
    return EstimatorClient("http://estimator", transport=transport)


@pytest.mark.parametrize(
    ("status", "code", "kind"),
    [
        (422, "invalid_request", InvalidRequestError),
        (401, "unauthorized", UnauthorizedError),
        (404, "not_found", SlideNotFoundError),
        (409, "conflict", ConflictError),
        (500, "replay_mismatch", ServerError),
        (503, "internal", ServerError),
        (409, "slide_log_corrupt", SlideLogCorruptError),
        (507, "storage_full", StorageFullError),
    ],
)
def test_the_code_chooses_the_exception(status: int, code: str, kind: type) -> None:
    estimator = client_answering(status, {"code": code, "detail": "anything at all"})
    with estimator, pytest.raises(kind) as raised:
        estimator.slide("abc")
    assert raised.value.status == status and raised.value.code == ErrorCode(code)
    assert raised.value.detail == "anything at all"


def test_a_reply_without_a_code_is_still_a_typed_error() -> None:
    estimator = client_answering(502, ["not", "an", "object"])
    with estimator, pytest.raises(ServerError):
        estimator.health()
    transport = httpx.MockTransport(lambda _: httpx.Response(400, text="<html>proxy</html>"))
    estimator = EstimatorClient("http://estimator", transport=transport)
    with estimator, pytest.raises(EstimatorError) as raised:
        estimator.list_slides()
    assert raised.value.code is ErrorCode.INVALID_REQUEST and "proxy" in str(raised.value)


def test_replies_are_typed_models() -> None:
    body = {"status": "ok", "slides": 3}
    with client_answering(200, body) as estimator:
        health = estimator.health()
    assert (health.status, health.slides) == ("ok", 3)
