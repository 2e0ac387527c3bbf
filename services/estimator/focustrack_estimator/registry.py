"""Every strategy the estimator serves, by name (the benchmarks add their oracle to it).

Each strategy module exports ``STRATEGIES: dict[str, Callable[..., Strategy]]``:
a factory called as ``factory(settings, **params)``, whose keyword parameters
all have defaults (the tuned defaults). A factory whose second parameter is
``options`` (a `FilterOptions`, with the strategy's defaults as its default)
takes the options' fields as parameters too: to a user they are parameters
like the others (``{"q": 0.2, "gate_nis": 9.0}``), to the code one dataclass.
`create` checks the parameters by name so that a typo is an error, not a
silently ignored setting.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping
from typing import Any

from focustrack_core.domain import SlideSettings
from focustrack_estimator import bank, classic, kalman_strategies, lean_scan, rescan, spatial
from focustrack_estimator.strategy import Cost, CostModel, Strategy

Factory = Callable[..., Strategy]

STRATEGIES: dict[str, Factory] = {
    **kalman_strategies.STRATEGIES,
    **bank.STRATEGIES,
    **spatial.STRATEGIES,
    **lean_scan.STRATEGIES,
    **rescan.STRATEGIES,
    **classic.STRATEGIES,
}

#: Each strategy's cost model, by the same names (a test keeps the two tables equal).
COSTS: dict[str, CostModel] = {
    **kalman_strategies.COSTS,
    **bank.COSTS,
    **spatial.COSTS,
    # kf-2d-lean wraps kf-2d at its default bank (its own parameters only pick frames);
    # kf-rescan keeps a few numbers per tile, as a 1-D filter does.
    "kf-2d-lean": lambda settings, _params: spatial.kf_2d_cost(settings, parameters("kf-2d")),
    "kf-rescan": kalman_strategies.path_cost(1),
    **classic.COSTS,
}


def _options_default(factory: Factory) -> Any | None:
    """The default `options` dataclass of a factory that takes one, else None."""
    options = inspect.signature(factory).parameters.get("options")
    return None if options is None else options.default


def parameters(name: str, strategies: Mapping[str, Factory] = STRATEGIES) -> dict[str, Any]:
    """The tunable parameters of strategy `name` (of `strategies`) with their defaults."""
    factory = _factory(name, strategies)
    own = {
        key: p.default
        for key, p in inspect.signature(factory).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    }
    options = _options_default(factory)
    return own if options is None else {**dataclasses.asdict(options), **own}


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
    options = _options_default(factory)
    if options is None:
        return factory(settings, **params)
    fields = {field.name for field in dataclasses.fields(options)}
    chosen = dataclasses.replace(options, **{k: v for k, v in params.items() if k in fields})
    return factory(settings, chosen, **{k: v for k, v in params.items() if k not in fields})


def _factory(name: str, strategies: Mapping[str, Factory]) -> Factory:
    if name not in strategies:
        raise ValueError(f"unknown strategy {name!r}; known: {', '.join(sorted(strategies))}")
    return strategies[name]


@dataclasses.dataclass(frozen=True)
class Catalogue:
    """The strategies a service serves, by name, and each one's cost model (same names).

    The estimator serves `SERVED`; `--strategies-from MODULE` serves a module's
    `CATALOGUE` instead (the benchmarks' adds `gp-oracle`: an opt-in).
    """

    strategies: Mapping[str, Factory]
    costs: Mapping[str, CostModel]

    def __post_init__(self) -> None:
        if set(self.strategies) != set(self.costs):
            missing = sorted(set(self.strategies) ^ set(self.costs))
            raise ValueError(f"every strategy needs a cost model and vice versa: {missing}")

    def parameters(self, name: str) -> dict[str, Any]:
        return parameters(name, self.strategies)

    def create(
        self, name: str, settings: SlideSettings, params: dict[str, Any] | None = None
    ) -> Strategy:
        return create(name, settings, params, self.strategies)

    def cost(
        self, name: str, settings: SlideSettings, params: Mapping[str, Any] | None = None
    ) -> Cost:
        """The projected cost of a slide of strategy `name` with `params` (over the defaults)."""
        resolved = {**self.parameters(name), **(params or {})}
        return self.costs[name](settings, resolved)


#: What the estimator serves by default.
SERVED = Catalogue(STRATEGIES, COSTS)
