"""The strategies the benchmarks compare: every served one, and the `gp-oracle` floor.

`CATALOGUE` is also what `focustrack serve estimator --strategies-from
focustrack.bench.strategies` serves: the oracle over REST, opted into.
"""

from __future__ import annotations

from typing import Any

from focustrack.bench.oracle import gp_oracle, gp_oracle_cost
from focustrack_core.domain import SlideSettings
from focustrack_estimator import registry
from focustrack_estimator.strategy import Strategy

STRATEGIES: dict[str, registry.Factory] = {**registry.STRATEGIES, "gp-oracle": gp_oracle}
CATALOGUE = registry.Catalogue(STRATEGIES, {**registry.COSTS, "gp-oracle": gp_oracle_cost})


def parameters(name: str) -> dict[str, Any]:
    """The tunable parameters of strategy `name` with their defaults."""
    return registry.parameters(name, STRATEGIES)


def create(name: str, settings: SlideSettings, params: dict[str, Any] | None = None) -> Strategy:
    """A new strategy `name`, served or the oracle; unknown names or parameters: ValueError."""
    return registry.create(name, settings, params, STRATEGIES)
