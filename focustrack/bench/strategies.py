"""The strategies the benchmarks compare: every served one, and the `gp-oracle` floor.

`CATALOGUE` is also what `focustrack serve estimator --strategies-from
focustrack.bench.strategies` serves: the oracle over REST, opted into.
"""

from __future__ import annotations

from typing import Any

from focustrack.bench.oracle import GP_ORACLE
from focustrack_core.domain import SlideSettings
from focustrack_estimator import registry
from focustrack_estimator.strategy import Strategy, StrategyEntry

STRATEGIES: dict[str, StrategyEntry[Any]] = {**registry.STRATEGIES, "gp-oracle": GP_ORACLE}
CATALOGUE = registry.Catalogue(STRATEGIES)


def parameters(name: str) -> dict[str, Any]:
    """Strategy `name`'s parameters at their defaults, as JSON gives them."""
    return CATALOGUE.parameters(name)


def create(name: str, settings: SlideSettings, params: registry.Params = None) -> Strategy:
    """A new strategy `name`, served or the oracle; unknown names or parameters: ValueError."""
    return CATALOGUE.create(name, settings, params)
