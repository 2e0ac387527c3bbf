"""How the scan waits for a service that is gone: timeouts, back-off and what is retried.

`RetryPolicy` holds the timeouts and the outages waited out (tenacity's exponential
back-off), and how many phase results the scan goes on without; the predicates say which
errors mean "nobody answered" (retried) and which are refusals (not retried). The engine
(`engine.py`) applies them to every call.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import httpx
import tenacity

from focustrack_client import EstimatorError
from focustrack_core.wire import rpc

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RetryPolicy:
    """Timeouts (s) and how long a gone service is waited for, retried with back-off."""

    instrument_timeout_s: float = 60.0  # one acquisition: a wide stack of big frames takes seconds
    instrument_outage_s: float = 60.0  # keep retrying a gone (or busy) instrument this long
    focus_timeout_s: float = 15.0
    phase_timeout_s: float = 15.0  # a phase stack's result; none by then: the tile has no phase
    #: phase stacks whose results the scan goes on without: it images the next tile while
    #: the phase service reconstructs (0: it waits for each result before going on)
    phase_in_flight: int = 1
    estimator_timeout_s: float = 10.0  # one HTTP request
    estimator_outage_s: float = 60.0  # keep retrying a gone estimator this long
    backoff_initial_s: float = 0.25  # the first pause between retries; it doubles ...
    backoff_max_s: float = 5.0  # ... up to this

    def __post_init__(self) -> None:
        times = (
            self.instrument_timeout_s,
            self.instrument_outage_s,
            self.focus_timeout_s,
            self.phase_timeout_s,
            self.estimator_timeout_s,
            self.estimator_outage_s,
            self.backoff_initial_s,
            self.backoff_max_s,
        )
        if min(times) <= 0:
            raise ValueError(f"timeouts must be positive, got {times}")
        if self.phase_in_flight < 0:
            raise ValueError(f"phase_in_flight must be >= 0, got {self.phase_in_flight}")

    def retrying(
        self,
        outage_s: float,
        retry_on: Callable[[BaseException], bool],
        what: str,
        on_retry: Callable[[], None] = lambda: None,
    ) -> tenacity.Retrying:
        """Calls retried while `retry_on` says so, pauses doubling, for up to `outage_s`;
        the last error is raised when that runs out. `on_retry` is called before each pause."""

        def before_sleep(state: tenacity.RetryCallState) -> None:
            on_retry()
            log.warning(
                "%s: attempt %d failed (%s); retrying",
                what,
                state.attempt_number,
                state.outcome.exception() if state.outcome is not None else "?",
            )

        return tenacity.Retrying(
            stop=tenacity.stop_after_delay(outage_s),
            wait=tenacity.wait_exponential(
                multiplier=self.backoff_initial_s, max=self.backoff_max_s
            ),
            retry=tenacity.retry_if_exception(retry_on),
            before_sleep=before_sleep,
            reraise=True,
        )


def instrument_retryable(error: BaseException) -> bool:
    """True when nobody answered (a Zenoh timeout, no queryable) or the instrument was busy,
    not when it refused the request."""
    return isinstance(error, rpc.RemoteError) and error.error.code in rpc.RETRYABLE


def estimator_retryable(error: BaseException) -> bool:
    """True for a connection error or a 5xx answer (a 4xx is a refusal)."""
    if isinstance(error, EstimatorError):
        return error.status >= 500
    return isinstance(error, httpx.TransportError)
