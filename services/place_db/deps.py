"""What the place database's routes are given: typed dependencies on the app's state (as
the FastAPI template's `deps.py`). The caller's identity comes from `fleetmap.services.auth`
(`Caller`, `Operator`, `RobotWriter`, `MaybeCaller`)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from fleetmap.fleet.map_render import MapRenderer
from fleetmap.fleet.map_scene import SceneCache
from fleetmap.place import PlaceDB
from fleetmap.services.place_db.config import Settings


async def get_db(request: Request) -> PlaceDB:
    """The place database the lifespan opened."""
    return request.app.state.db


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_renderer(request: Request) -> MapRenderer:
    """The live map's cloud and picture builder (cached per robot)."""
    return request.app.state.renderer


async def get_scene(request: Request) -> SceneCache:
    """The operator page's 3D view: robot clouds in their binary layout, cached."""
    return request.app.state.scene3d


Database = Annotated[PlaceDB, Depends(get_db)]
PlaceSettings = Annotated[Settings, Depends(get_settings)]
Renderer = Annotated[MapRenderer, Depends(get_renderer)]
Scene = Annotated[SceneCache, Depends(get_scene)]
