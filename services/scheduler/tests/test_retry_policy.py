"""The engine's retry policy: what is retried (no answer, BUSY) and what is not (a refusal)."""

from __future__ import annotations

import pytest

from focustrack_core.v1 import common_pb2
from focustrack_core.wire import rpc
from focustrack_scheduler.retry import RetryPolicy, instrument_retryable


def remote(code: int) -> rpc.RemoteError:
    return rpc.RemoteError(common_pb2.Error(code=code, message="test"))


def test_unanswered_and_busy_are_retried_until_the_call_succeeds() -> None:
    policy = RetryPolicy(backoff_initial_s=0.001, backoff_max_s=0.002)
    failures = [
        remote(common_pb2.ERROR_CODE_UNAVAILABLE),
        remote(common_pb2.ERROR_CODE_TIMEOUT),
        remote(common_pb2.ERROR_CODE_BUSY),
    ]

    def call() -> str:
        if failures:
            raise failures.pop(0)
        return "acquired"

    assert policy.retrying(60, instrument_retryable, "test")(call) == "acquired"
    assert not failures


def test_a_refusal_is_raised_at_once_and_an_outage_ends_with_the_last_error() -> None:
    policy = RetryPolicy(backoff_initial_s=0.001, backoff_max_s=0.002)
    calls: list[int] = []

    def refused() -> None:
        calls.append(1)
        raise remote(common_pb2.ERROR_CODE_Z_OUT_OF_RANGE)

    with pytest.raises(rpc.RemoteError, match="Z_OUT_OF_RANGE"):
        policy.retrying(60, instrument_retryable, "test")(refused)
    assert len(calls) == 1

    def gone() -> None:
        calls.append(1)
        raise remote(common_pb2.ERROR_CODE_UNAVAILABLE)

    with pytest.raises(rpc.RemoteError, match="UNAVAILABLE"):
        policy.retrying(0.05, instrument_retryable, "test")(gone)
    assert len(calls) > 2  # tried again, with pauses, until the outage allowance ran out
    with pytest.raises(ValueError, match="positive"):
        RetryPolicy(instrument_outage_s=0)
