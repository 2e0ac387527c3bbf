"""A strategy's parameters: a slide's `params` over the strategy's defaults, checked."""

from __future__ import annotations

from typing import Any

from focustrack_estimator import registry
from focustrack_estimator.errors import SlideError


def resolve_params(
    strategy: str, params: dict[str, Any], catalogue: registry.Catalogue = registry.SERVED
) -> dict[str, Any]:
    """The strategy's full parameter set: `params` over the defaults, each of the default's type."""
    try:
        defaults = catalogue.parameters(strategy)
    except ValueError as error:
        raise SlideError(str(error), ("body", "strategy")) from None
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise SlideError(
            f"unknown parameter(s) {', '.join(unknown)} for strategy {strategy!r}; "
            f"known: {', '.join(defaults) or 'none'}",
            ("body", "params"),
        )
    resolved = dict(defaults)
    for name, value in params.items():
        resolved[name] = _physical(strategy, name, _coerce(strategy, name, value, defaults[name]))
    return resolved


#: Magnitudes a strategy parameter may have (zero aside): beyond, its products with other
#: quantities under- or overflow a float (1e-300 squared is 0), and it is no physical
#: noise, length or sigma anyway (the smallest default is 1e-10).
PARAM_MAGNITUDES = (1e-30, 1e30)


def _physical(strategy: str, name: str, value: Any) -> Any:
    """`value`, or a SlideError if it (or an element of it) is a non-physical magnitude."""
    low, high = PARAM_MAGNITUDES
    numbers = value if isinstance(value, tuple) else (value,)
    for number in numbers:
        real = isinstance(number, float | int) and not isinstance(number, bool)
        if real and number != 0 and not low <= abs(number) <= high:
            raise SlideError(
                f"parameter {name!r} of strategy {strategy!r} is not a physical value "
                f"(magnitudes from {low:g} to {high:g}, or 0, are): {number!r}",
                ("body", "params", name),
            )
    return value


def _coerce(strategy: str, name: str, value: Any, default: Any) -> Any:
    if value is None or default is None:  # None asks for the default; a None default takes any
        return default if value is None else value
    numbers = isinstance(value, list) and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    )
    if isinstance(default, tuple) and numbers:
        return tuple(float(v) for v in value)
    kind = type(default)
    if kind is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if kind is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind in (bool, str) and isinstance(value, kind):
        return value
    raise SlideError(
        f"parameter {name!r} of strategy {strategy!r} must be a {kind.__name__} "
        f"(default {default!r}), got {value!r}",
        ("body", "params", name),
    )
