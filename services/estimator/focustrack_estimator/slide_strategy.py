"""A slide's strategy from its configuration: the service's one door to the strategies.

Everything the service asks of the strategies' catalogue goes through here: a
slide's parameters resolved over its strategy's defaults (once per request, into the
strategy's parameters model), its strategy built, its cost projected, and the trial
scan that creation runs. Importing this module
imports every strategy (scipy, filterpy: most of the service's start-up time), so
the live slides (`slides`) import it when the first slide is used.
"""

from __future__ import annotations

from focustrack_client import models as api
from focustrack_core.domain import Measurement
from focustrack_core.rest import to_domain
from focustrack_estimator import registry
from focustrack_estimator.errors import STRATEGY_ERRORS, SlideError
from focustrack_estimator.params import resolve_params
from focustrack_estimator.strategy import Cost, Strategy, StrategyParams


def served(catalogue: registry.Catalogue | None) -> registry.Catalogue:
    """`catalogue`, or the estimator's own strategies when None."""
    return registry.SERVED if catalogue is None else catalogue


def resolved_params(config: api.SlideCreate, catalogue: registry.Catalogue) -> StrategyParams:
    """The slide's parameters over its strategy's defaults, checked (SlideError if not)."""
    return resolve_params(config.strategy, config.params, catalogue)


def stored_config(config: api.SlideCreate, params: StrategyParams) -> api.SlideCreate:
    """`config` with every parameter resolved (`params`), as it is stored and served."""
    return config.model_copy(update={"params": params.model_dump(mode="json")})


def _created(
    config: api.SlideCreate, params: StrategyParams, catalogue: registry.Catalogue
) -> Strategy:
    """The slide's strategy; any of `STRATEGY_ERRORS` if it refuses its configuration."""
    return catalogue.create(config.strategy, to_domain.slide_settings(config), params)


def new_strategy(
    config: api.SlideCreate, params: StrategyParams, catalogue: registry.Catalogue
) -> Strategy:
    """The slide's strategy, its first acquisition planned: absurd parameters fail there,
    at creation (a SlideError)."""
    try:
        strategy = _created(config, params, catalogue)
        strategy.next_acquisition()
        return strategy
    except STRATEGY_ERRORS as error:
        raise SlideError(
            f"strategy {config.strategy!r} rejected its settings or parameters: {error}",
            ("body",),
        ) from None


def cost_of(config: api.SlideCreate, params: StrategyParams, catalogue: registry.Catalogue) -> Cost:
    """The projected cost of a slide (its strategy's cost model, with its parameters)."""
    return catalogue.cost(config.strategy, to_domain.slide_settings(config), params)


#: Tiles per side of the trial scan of `probe` (fewer where the slide has fewer).
PROBE_SIDE = 4


def probe(config: api.SlideCreate, params: StrategyParams, catalogue: registry.Catalogue) -> None:
    """Scan a small grid (at most `PROBE_SIDE` a side) with the slide's strategy, settings and
    parameters, with the sharpest measurements the API allows, jumping up and down, then
    make its map; a SlideError if the strategy fails on the way.

    Bounds on each value cannot see every combination that breaks the arithmetic (a
    slope sigma of 1e30 with a 1 nm measurement made P singular): a slide whose
    strategy fails this probe would fail on a real scan too and stay stuck there.
    """
    grid = config.grid.model_copy(
        update={
            "rows": min(config.grid.rows, PROBE_SIDE),
            "cols": min(config.grid.cols, PROBE_SIDE),
        }
    )
    try:
        strategy = _created(config.model_copy(update={"grid": grid}), params, catalogue)
    except STRATEGY_ERRORS:
        return  # a strategy that needs a larger grid (a survey): the slide's own was built
    try:
        while (acquisition := strategy.next_acquisition()) is not None:
            jump_um = 10.0 * config.dof_um * (-1) ** acquisition.index
            measurement = Measurement(acquisition.z.center_um + jump_um, api.MIN_SIGMA_UM)
            strategy.record(acquisition, measurement)
        strategy.focus_map()
    except STRATEGY_ERRORS as error:
        raise SlideError(
            f"strategy {config.strategy!r} with these settings and parameters fails on a "
            f"{grid.rows}x{grid.cols} trial scan ({type(error).__name__}: {error}): "
            "they are not usable (non-physical values?)",
            ("body",),
        ) from None
