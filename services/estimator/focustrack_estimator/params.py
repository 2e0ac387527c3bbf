"""Strategy parameters at the REST edge: a slide's `params` resolved once into its strategy's
model, and every strategy's model published in the OpenAPI document.

The request model (`focustrack_client.models.SlideCreate`) takes `params` as a JSON
object of any names, as the client cannot know the served strategies; the estimator
validates it with the model of the strategy `strategy` names (`resolve_params`) and
describes it in its OpenAPI document as any of those models (`publish_params`), which
`GET /v1/strategies` lists by strategy (`strategy_infos`).
"""

from __future__ import annotations

from typing import Any

from pydantic.json_schema import models_json_schema

from focustrack_client.models import StrategyInfo
from focustrack_estimator import registry
from focustrack_estimator.errors import SlideError
from focustrack_estimator.strategy import StrategyParams


def resolve_params(
    strategy: str, params: dict[str, Any], catalogue: registry.Catalogue = registry.SERVED
) -> StrategyParams:
    """The strategy's parameters: `params` over its defaults, validated by its model; a
    SlideError (422) located at the first bad parameter, or at the strategy if unknown."""
    try:
        return catalogue.params(strategy, params)
    except registry.ParamsError as error:
        raise SlideError(str(error), ("body", "params", error.name)) from None
    except ValueError as error:
        raise SlideError(str(error), ("body", "strategy")) from None


def strategy_infos(catalogue: registry.Catalogue) -> list[StrategyInfo]:
    """Every strategy of `catalogue` with its parameters' schema and defaults, by name."""
    return [
        StrategyInfo(
            name=name,
            parameters=entry.params.model_json_schema(),
            defaults=entry.params().model_dump(mode="json"),
        )
        for name, entry in sorted(catalogue.strategies.items())
    ]


#: What `SlideCreate.params` says in the OpenAPI document beside its models.
PARAMS_NOTE = (
    "Null takes a parameter's default too. The object is the parameters model of the "
    "strategy `strategy` names (`x-strategy-params` maps each name to its model; GET "
    "/v1/strategies lists them with their defaults); every number in it is 0 or of a "
    "magnitude from 1e-30 to 1e30."
)


def publish_params(openapi: dict[str, Any], catalogue: registry.Catalogue) -> None:
    """Add each strategy's parameters model of `catalogue` to the OpenAPI document's
    components, and describe `SlideCreate.params` and `StrategyInfo.defaults` as any of them.

    `openapi` is changed in place (FastAPI's `app.openapi()`, which it keeps).
    """
    models = {name: entry.params for name, entry in sorted(catalogue.strategies.items())}
    unique = list(dict.fromkeys(models.values()))
    keys, schema = models_json_schema(
        [(model, "validation") for model in unique], ref_template="#/components/schemas/{model}"
    )
    components = openapi.setdefault("components", {}).setdefault("schemas", {})
    components.update(schema.get("$defs", {}))
    ref = {model: keys[(model, "validation")] for model in unique}
    any_of = [ref[model] for model in unique]
    for component, body in components.items():
        properties = body.get("properties", {})
        if component.startswith("SlideCreate") and "params" in properties:
            properties["params"] = {
                "anyOf": any_of,
                "title": "Params",
                "description": f"{properties['params'].get('description', '')}. {PARAMS_NOTE}",
                "x-strategy-params": {name: ref[model] for name, model in models.items()},
            }
        if component == StrategyInfo.__name__:
            properties["defaults"] = {**properties["defaults"], "anyOf": any_of}
            properties["defaults"].pop("type", None)
            properties["defaults"].pop("additionalProperties", None)
