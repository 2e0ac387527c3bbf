"""Strategies: the ones served, each with its parameters (under /v1)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter

from focustrack_client.models import StrategyInfo
from focustrack_estimator.dependencies import SlidesDep

router = APIRouter(prefix="/v1", tags=["strategies"])


@router.get("/strategies")
async def list_strategies(slides: SlidesDep) -> list[StrategyInfo]:
    """The strategies served, each with its parameters: their JSON schema (types, units,
    bounds) and defaults."""
    return await asyncio.to_thread(slides.strategies)
