"""The operator page's 3D view: each robot's cloud in a compact binary layout, the scene's
overlap lines, and the vendored three.js files (served from here: no CDN, works offline)."""

from __future__ import annotations

from pathlib import Path as FsPath
from typing import Literal

from fastapi import APIRouter, Depends, Path, Query, Response
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from fleetmap.errors import NotSolved, UnknownRobot
from fleetmap.fleet.map_document import map_document
from fleetmap.fleet.map_render import BASE_VOXEL_M
from fleetmap.fleet.map_scene import DEFAULT_VOXEL_M, overlap_lines
from fleetmap.mapcloud import ROBOT_COLOURS
from fleetmap.services.auth import require_operator
from fleetmap.services.http_errors import ERROR_RESPONSES
from fleetmap.services.place_db.deps import Database, Renderer, Scene

router = APIRouter(responses=ERROR_RESPONSES)
STATIC = FsPath(__file__).parent / "static"
ROBOT = Path(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")


def install_static(app) -> None:
    """The page's module script and three.js under /static/map3d (no token: code only)."""
    app.mount("/static/map3d", StaticFiles(directory=STATIC), name="map3d")


@router.get(
    "/map/robots/{robot}/cloud.bin",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def robot_cloud(
    db: Database,
    scene: Scene,
    robot: str = ROBOT,
    voxel: float = Query(
        DEFAULT_VOXEL_M, ge=BASE_VOXEL_M, le=1.0, allow_inf_nan=False, description="metres"
    ),
    frame: Literal["own", "reference"] = Query(
        "own", description="own: the robot's map frame; reference: placed, drift-corrected"
    ),
) -> Response:
    """One robot's map cloud, voxelised and capped at 100 000 points: N float32 x y z, then
    N uint8 r g b (image colour); `x-points: N`, `x-frame: own|reference`. In ITS OWN map
    frame by default (apply `transforms[robot]` of `GET /map`; cached until the robot gains
    views); with `frame=reference` in the reference frame, each point moved with its
    keyframe's drift correction where the keyframe graph corrects the robot (a bent map has
    no single transform), else by `transforms[robot]`; 404 if the robot is not placed."""
    if db.robot_code(robot) is None:
        raise UnknownRobot(f"Unknown robot {robot!r}")
    m = map_document(db) if frame == "reference" else None
    if m is not None and robot not in m["transforms"]:
        raise NotSolved(f"robot {robot!r} is not placed in the live map (version {m['version']})")
    body = scene.robot_cloud(robot, len(db.view_ids(robot)), voxel, m)
    headers = {"x-points": str(len(body) // 15), "x-frame": frame, "cache-control": "no-store"}
    return Response(body, media_type="application/octet-stream", headers=headers)


@router.get("/map/lines", dependencies=[Depends(require_operator)])
async def map_lines(db: Database, renderer: Renderer) -> dict:
    """The verified overlaps between placed robots as lines between their keyframes'
    camera positions, in the reference frame: rows [robot_a, robot_b, xa, ya, za, xb, yb,
    zb], with the map's version and each robot's colour (RGB in 0..1, as the pictures)."""

    def build() -> dict:
        m = map_document(db)
        colours = {
            r: ROBOT_COLOURS[k % len(ROBOT_COLOURS)].tolist() for k, r in enumerate(m["robots"])
        }
        lines = overlap_lines(db, renderer, m)
        return {"version": m["version"], "colours": colours, "overlaps": lines}

    return await run_in_threadpool(build)
