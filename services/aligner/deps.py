"""What the aligner's routes are given: typed dependencies on the app's state (as the
FastAPI template's `deps.py`); the caller's identity from `fleetmap.services.auth`."""

from __future__ import annotations

from collections import OrderedDict
from typing import Annotated

from fastapi import Depends, Request

from fleetmap.services.aligner.budget import PixelBudget
from fleetmap.services.aligner.config import Settings


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_budget(request: Request) -> PixelBudget:
    """Pixels and heavy requests in flight in this process."""
    return request.app.state.pixels


async def get_clouds(request: Request) -> OrderedDict:
    """Merged clouds kept for `GET /clouds/{id}`: id -> (PLY bytes, points), oldest first."""
    return request.app.state.clouds


AlignerSettings = Annotated[Settings, Depends(get_settings)]
Budget = Annotated[PixelBudget, Depends(get_budget)]
Clouds = Annotated[OrderedDict, Depends(get_clouds)]
