"""The errors of the estimator's domain: requests it refuses, and logs that no longer replay.

They say what is wrong, not how a protocol reports it: the REST layer maps each type
to its HTTP status and error code (`handlers`).
"""

from __future__ import annotations

import numpy as np


class SlideError(Exception):
    """A request the domain refuses: invalid input, or a slide over the service's limits.

    `where` locates the offending input, as a validation error's `loc` does
    (("body", "params", "q")): a refusal from the domain reads like one from the schema.
    """

    def __init__(self, message: str, where: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.where = where


class SlideNotFoundError(SlideError):
    """No slide of that id."""


class SlideConflictError(SlideError):
    """The request contradicts the slide's state (not the pending acquisition, a re-post
    with a different value, a finished scan, a log another writer moved on)."""


class StrategyNotServedError(SlideConflictError):
    """The slide's strategy is not among those this service was started to serve (a slide
    made under `--strategies-from MODULE`, the service started again without it)."""


class ReplayMismatchError(SlideError):
    """The stored log no longer replays to the logged outcomes (the strategy changed)."""


#: Exceptions a strategy may raise on absurd parameters or input (the domain turns them
#: into a SlideError).
STRATEGY_ERRORS = (ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError)
