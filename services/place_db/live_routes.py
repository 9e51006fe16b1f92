"""Live map routes of the place database: the map, its cloud, trajectories and picture, the
stored views, and the operator page."""

from __future__ import annotations

import asyncio
import base64

from fastapi import APIRouter, Depends, Path, Query, Request, Response
from fastapi.responses import HTMLResponse
from starlette.concurrency import run_in_threadpool

from fleetmap.errors import NotSolved
from fleetmap.fleet.map_document import map_document
from fleetmap.fleet.map_render import BASE_VOXEL_M
from fleetmap.fleet.state import read_graph_g2o, read_placement
from fleetmap.mapcloud import ply_bytes
from fleetmap.services.auth import require_operator
from fleetmap.services.http_errors import ERROR_RESPONSES
from fleetmap.services.place_db import schemas as s
from fleetmap.services.place_db.deps import Database, Renderer
from fleetmap.services.place_db.page import CSP, PAGE
from fleetmap.view import media_type

router = APIRouter(responses=ERROR_RESPONSES)
KF_ID = Path(ge=1, le=2**63 - 1)


async def run_in_map_pool(request: Request, fn, *args):
    """The cloud, picture and trajectories built on their own threads (`app.state.map_pool`,
    two): however many wait, the other routes and /healthz keep the server's thread pool."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(request.app.state.map_pool, fn, *args)


@router.get(
    "/map",
    response_model=s.LiveMap,
    response_model_exclude_unset=True,  # null `reference` stays; absent extras stay absent
    dependencies=[Depends(require_operator)],
)
async def live_map(db: Database) -> s.LiveMap:
    """The live fleet map: each placed robot's transform into the reference robot's map
    frame (`transforms[R]` maps R's map points into the reference's), the robots not placed
    with the reason, and the merge worker's pair states. `version` changes only when the
    placement does."""
    return s.LiveMap(**await run_in_threadpool(map_document, db))


@router.get(
    "/map/cloud.ply",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
async def map_cloud(
    request: Request,
    db: Database,
    renderer: Renderer,
    voxel: float = Query(
        0.05, ge=BASE_VOXEL_M, le=1.0, allow_inf_nan=False, description="voxel size in metres"
    ),
) -> Response:
    """The merged cloud of the placed robots (binary PLY: x y z, image colour, per-point
    `robot` index in the order of the map's `robots`), in the reference frame."""

    def build() -> bytes:
        return ply_bytes(*renderer.cloud(map_document(db), voxel))

    body = await run_in_map_pool(request, build)
    return Response(body, media_type="application/octet-stream")


@router.get(
    "/map/overview.png",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"image/png": {}}}},
)
async def map_overview(request: Request, db: Database, renderer: Renderer) -> Response:
    """Top-down picture of the live map: placed robots' clouds and keyframe tracks."""

    def build() -> bytes:
        return renderer.overview(map_document(db))

    return Response(await run_in_map_pool(request, build), media_type="image/png")


@router.get(
    "/map/trajectories",
    response_model=dict[str, list[list[float]]],
    dependencies=[Depends(require_operator)],
)
async def map_trajectories(request: Request, db: Database, renderer: Renderer) -> dict:
    """Each placed robot's keyframe poses in the reference frame: rows [stamp, tx, ty, tz,
    qx, qy, qz, qw] (TUM order), in time order."""

    def build() -> dict:
        return renderer.trajectories(map_document(db))

    return await run_in_map_pool(request, build)


@router.get(
    "/map/pose_graph.g2o",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}}},
)
def map_pose_graph(db: Database) -> Response:
    """The live map's keyframe pose graph in g2o's SE3 format (as `fleetmap merge` writes
    pose_graph.g2o): one vertex per keyframe of every placed robot at its corrected pose,
    odometry and the loop closures the robust solve kept. 404 until a graph has been solved
    on the current placement (or where none is built: no robot's path long enough to bend,
    or `correct_drift` off)."""
    version = read_placement(db).version
    text = read_graph_g2o(db, version)
    if text is None:
        raise NotSolved(f"no keyframe pose graph solved on the live map's placement {version}")
    return Response(text, media_type="text/plain")


@router.get(
    "/keyframes/{kf_id}/view",
    response_model=s.KeyframeView,
    dependencies=[Depends(require_operator)],
)
def keyframe_view(db: Database, kf_id: int = KF_ID) -> s.KeyframeView:
    """A keyframe's stored RGB-D view: the images (base64) with the frame's pose and
    intrinsics; 404 for a keyframe posted without one."""
    rgb, depth = db.view_bytes(kf_id)
    frame = db.load_frame(kf_id)
    return s.KeyframeView(
        keyframe_id=kf_id,
        robot_id=frame.robot_id,
        stamp=frame.stamp,
        width=frame.width,
        height=frame.height,
        intrinsics=frame.intrinsics.to_dict(),
        T_map_cam=frame.T_map_cam.tolist(),
        rgb_type=media_type(rgb),
        rgb=base64.b64encode(rgb).decode(),
        depth=base64.b64encode(depth).decode(),
    )


@router.get(
    "/keyframes/{kf_id}/view/{part}",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}, "image/png": {}}}},
)
def keyframe_view_image(db: Database, part: s.ViewPart, kf_id: int = KF_ID) -> Response:
    """One image of a keyframe's stored view as posted (colour JPEG, depth 16-bit PNG)."""
    rgb, depth = db.view_bytes(kf_id)
    data = rgb if part == "rgb" else depth
    return Response(data, media_type=media_type(data))


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def operator_page() -> HTMLResponse:
    """The operator page: a shell without data; its script reads the map with the token
    given in the address (#token=...) or typed in, sent as a bearer header."""
    return HTMLResponse(PAGE, headers={"cache-control": "no-store", "content-security-policy": CSP})
