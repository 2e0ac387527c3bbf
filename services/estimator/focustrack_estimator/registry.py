"""Every strategy the estimator serves, by name (the benchmarks add their oracle to it).

Each strategy module exports ``STRATEGIES: dict[str, Callable[..., Strategy]]``:
a factory called as ``factory(settings, **params)``, whose keyword parameters
all have defaults (the tuned defaults). `create` checks the parameters by name
so that a typo is an error, not a silently ignored setting.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from typing import Any

from focustrack_estimator import bank, classic, kalman_strategies, spatial
from focustrack_estimator.strategy import SlideSettings, Strategy

Factory = Callable[..., Strategy]

STRATEGIES: dict[str, Factory] = {
    **kalman_strategies.STRATEGIES,
    **bank.STRATEGIES,
    **spatial.STRATEGIES,
    **classic.STRATEGIES,
}


def parameters(name: str, strategies: Mapping[str, Factory] = STRATEGIES) -> dict[str, Any]:
    """The tunable parameters of strategy `name` (of `strategies`) with their defaults."""
    signature = inspect.signature(_factory(name, strategies))
    return {
        key: p.default
        for key, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }


def create(
    name: str,
    settings: SlideSettings,
    params: dict[str, Any] | None = None,
    strategies: Mapping[str, Factory] = STRATEGIES,
) -> Strategy:
    """A new strategy `name` for a slide; unknown names or parameters raise ValueError."""
    factory = _factory(name, strategies)
    params = params or {}
    known = parameters(name, strategies)
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)} for strategy {name!r}; "
            f"known: {', '.join(known) or 'none'}"
        )
    return factory(settings, **params)


def _factory(name: str, strategies: Mapping[str, Factory]) -> Factory:
    if name not in strategies:
        raise ValueError(f"unknown strategy {name!r}; known: {', '.join(sorted(strategies))}")
    return strategies[name]
