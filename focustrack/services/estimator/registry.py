"""Every strategy by name: the one list the benchmark, the estimator service and the CLI share.

Each strategy module exports ``STRATEGIES: dict[str, Callable[..., Strategy]]``:
a factory called as ``factory(settings, **params)``, whose keyword parameters
all have defaults (the tuned defaults). `create` checks the parameters by name
so that a typo is an error, not a silently ignored setting.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from focustrack.services.estimator import bank, classic, kalman_strategies, spatial
from focustrack.services.estimator.strategy import SlideSettings, Strategy

STRATEGIES: dict[str, Callable[..., Strategy]] = {
    **kalman_strategies.STRATEGIES,
    **bank.STRATEGIES,
    **spatial.STRATEGIES,
    **classic.STRATEGIES,
}


def parameters(name: str) -> dict[str, Any]:
    """The tunable parameters of strategy `name` with their defaults."""
    signature = inspect.signature(_factory(name))
    return {
        key: p.default
        for key, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }


def create(name: str, settings: SlideSettings, params: dict[str, Any] | None = None) -> Strategy:
    """A new strategy `name` for a slide; unknown names or parameters raise ValueError."""
    factory = _factory(name)
    params = params or {}
    unknown = sorted(set(params) - set(parameters(name)))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)} for strategy {name!r}; "
            f"known: {', '.join(parameters(name)) or 'none'}"
        )
    return factory(settings, **params)


def _factory(name: str) -> Callable[..., Strategy]:
    if name not in STRATEGIES:
        raise ValueError(f"unknown strategy {name!r}; known: {', '.join(sorted(STRATEGIES))}")
    return STRATEGIES[name]
