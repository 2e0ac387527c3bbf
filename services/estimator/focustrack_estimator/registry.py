"""Every strategy the estimator serves, by name (the benchmarks add their oracle to it).

Each strategy module exports ``STRATEGIES: dict[str, StrategyEntry]``: per
strategy its parameters' model (`StrategyParams`: every parameter's name, type,
default, unit and bounds), its factory and its cost model, both called as
``f(settings, params)`` with the parameters validated by that model. To a user
the parameters are a JSON object (``{"q": 0.2, "gate_nis": 9.0}``, omitted ones
at their defaults, a typo an error); to the code one typed model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from focustrack_core.domain import SlideSettings
from focustrack_estimator import (
    bank,
    classic,
    kalman_strategies,
    laser,
    lean_scan,
    nshp,
    rescan,
    spatial,
)
from focustrack_estimator.strategy import Cost, Strategy, StrategyEntry, StrategyParams

STRATEGIES: dict[str, StrategyEntry[Any]] = {
    **kalman_strategies.STRATEGIES,
    **bank.STRATEGIES,
    **spatial.STRATEGIES,
    **nshp.STRATEGIES,
    **lean_scan.STRATEGIES,
    **laser.STRATEGIES,
    **rescan.STRATEGIES,
    **classic.STRATEGIES,
}

#: Parameters as a caller may give them: a model, a JSON object (over the defaults) or None.
Params = StrategyParams | Mapping[str, Any] | None


class ParamsError(ValueError):
    """Parameters a strategy's model refuses; the message names the parameter (`name`), the
    rule and the value given, or the known parameters where `name` is not one of them."""

    def __init__(self, message: str, name: str) -> None:
        super().__init__(message)
        self.name = name


def _refusal(strategy: str, model: type[StrategyParams], error: ValidationError) -> ParamsError:
    """The first of `error`'s complaints, in words (pydantic's own do not name the strategy
    nor, for an unknown parameter, the known ones)."""
    first = error.errors()[0]
    name = str(first["loc"][0]) if first["loc"] else ""
    if name not in model.model_fields:
        known = ", ".join(model.model_fields) or "none"
        return ParamsError(
            f"unknown parameter {name!r} for strategy {strategy!r}; known: {known}", name
        )
    default = model.model_fields[name].default
    return ParamsError(
        f"parameter {name!r} of strategy {strategy!r} (default {default!r}): {first['msg']}; "
        f"got {first['input']!r}",
        name,
    )


@dataclass(frozen=True)
class Catalogue:
    """The strategies a service serves, by name.

    The estimator serves `SERVED`; `--strategies-from MODULE` serves a module's
    `CATALOGUE` instead (the benchmarks' adds `gp-oracle`: an opt-in).
    """

    strategies: Mapping[str, StrategyEntry[Any]]

    def entry(self, name: str) -> StrategyEntry[Any]:
        """Strategy `name`'s entry; a ValueError naming the known ones if there is none."""
        if name not in self.strategies:
            known = ", ".join(sorted(self.strategies))
            raise ValueError(f"unknown strategy {name!r}; known: {known}")
        return self.strategies[name]

    def params(self, name: str, params: Params = None) -> StrategyParams:
        """Strategy `name`'s parameters: `params` (a JSON object: over the defaults) validated
        by its model; a `ParamsError` naming the first bad parameter."""
        model = self.entry(name).params
        if isinstance(params, StrategyParams):
            if not isinstance(params, model):
                raise TypeError(
                    f"strategy {name!r} takes {model.__name__}, not {type(params).__name__}"
                )
            return params
        try:
            return model.model_validate(params or {})
        except ValidationError as error:
            raise _refusal(name, model, error) from None

    def parameters(self, name: str) -> dict[str, Any]:
        """Strategy `name`'s parameters at their defaults, as JSON gives them."""
        return self.params(name).model_dump(mode="json")

    def create(self, name: str, settings: SlideSettings, params: Params = None) -> Strategy:
        """A new strategy `name` for a slide (`params` as `params` takes them)."""
        return self.entry(name).factory(settings, self.params(name, params))

    def cost(self, name: str, settings: SlideSettings, params: Params = None) -> Cost:
        """The projected cost of a slide of strategy `name` with `params`."""
        return self.entry(name).cost(settings, self.params(name, params))


#: What the estimator serves by default.
SERVED = Catalogue(STRATEGIES)


def create(name: str, settings: SlideSettings, params: Params = None) -> Strategy:
    """A new served strategy `name` (`Catalogue.create` of `SERVED`)."""
    return SERVED.create(name, settings, params)


def parameters(name: str) -> dict[str, Any]:
    """A served strategy's parameters at their defaults (`Catalogue.parameters` of `SERVED`)."""
    return SERVED.parameters(name)
