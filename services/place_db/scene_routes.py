"""The operator page's 3D view: each robot's cloud in a compact binary layout, the scene's
overlap lines, and the vendored three.js files (served from here: no CDN, works offline)."""

from __future__ import annotations

from pathlib import Path as FsPath

from fastapi import APIRouter, Depends, Path, Query, Request, Response
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from fleetmap.errors import UnknownRobot
from fleetmap.mapcloud import ROBOT_COLOURS
from fleetmap.place.live_view import BASE_VOXEL_M, map_document
from fleetmap.place.scene3d import DEFAULT_VOXEL_M, SceneCache, overlap_lines
from fleetmap.services.common import ERROR_RESPONSES, operator_only

router = APIRouter(responses=ERROR_RESPONSES)
STATIC = FsPath(__file__).parent / "static"
ROBOT = Path(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")


def install_static(app) -> None:
    """The page's module script and three.js under /static/map3d (no token: code only)."""
    app.mount("/static/map3d", StaticFiles(directory=STATIC), name="map3d")


def _scene(request: Request) -> SceneCache:
    state = request.app.state
    if getattr(state, "scene3d", None) is None:
        state.scene3d = SceneCache(state.renderer)
    return state.scene3d


@router.get(
    "/map/robots/{robot}/cloud.bin",
    dependencies=[Depends(operator_only)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def robot_cloud(
    request: Request,
    robot: str = ROBOT,
    voxel: float = Query(DEFAULT_VOXEL_M, ge=BASE_VOXEL_M, le=1.0, description="metres"),
) -> Response:
    """One robot's map cloud in ITS OWN map frame (apply `transforms[robot]` of `GET /map`),
    voxelised and capped at 100 000 points: N float32 x y z, then N uint8 r g b (image
    colour); `x-points: N`. Cached until the robot gains views."""
    store = request.app.state.db.store
    code = store.robot_code(robot)
    if code is None:
        raise UnknownRobot(f"Unknown robot {robot!r}")
    body = _scene(request).robot_cloud(robot, len(store.view_ids(code)), voxel)
    headers = {"x-points": str(len(body) // 15), "cache-control": "no-store"}
    return Response(body, media_type="application/octet-stream", headers=headers)


@router.get("/map/lines", dependencies=[Depends(operator_only)])
async def map_lines(request: Request) -> dict:
    """The verified overlaps between placed robots as lines between their keyframes'
    camera positions, in the reference frame: rows [robot_a, robot_b, xa, ya, za, xb, yb,
    zb], with the map's version and each robot's colour (RGB in 0..1, as the pictures)."""

    def build() -> dict:
        app = request.app.state
        m = map_document(app.db)
        colours = {
            r: ROBOT_COLOURS[k % len(ROBOT_COLOURS)].tolist() for k, r in enumerate(m["robots"])
        }
        lines = overlap_lines(app.db, app.renderer, m)
        return {"version": m["version"], "colours": colours, "overlaps": lines}

    return await run_in_threadpool(build)
