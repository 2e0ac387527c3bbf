"""Strategies: the ones served, each with its parameters (under /v1)."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, Field

from focustrack_estimator.dependencies import SlidesDep

router = APIRouter(prefix="/v1", tags=["strategies"])


class StrategyInfo(BaseModel):
    """A served strategy and its parameters (`GET /v1/strategies`)."""

    name: str = Field(description="The strategy's name, as `SlideCreate.strategy` takes it")
    parameters: dict[str, Any] = Field(
        description="The JSON schema of its parameters: each one's type, default, unit (in "
        "its name or its description) and bounds"
    )
    defaults: dict[str, Any] = Field(
        description="Every parameter at its default: a slide created without `params` has these"
    )


@router.get("/strategies")
async def list_strategies(slides: SlidesDep) -> list[StrategyInfo]:
    """The strategies served, each with its parameters: their JSON schema (types, units,
    bounds) and defaults."""
    return await asyncio.to_thread(slides.strategies)
