"""Place database routes: each parses input, calls one core function, returns a schema."""

from __future__ import annotations

import asyncio
import time
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from fleetmap.errors import BadInput, PayloadTooLarge
from fleetmap.frame import decode
from fleetmap.place import Candidate, PlaceDB
from fleetmap.place.nominate import nominated_overlaps
from fleetmap.services.auth import (
    MaybeCaller,
    RobotWriter,
    auth_summary,
    require_operator,
    require_token,
)
from fleetmap.services.body import read_body
from fleetmap.services.http_errors import ERROR_RESPONSES
from fleetmap.services.place_db import schemas as s
from fleetmap.services.place_db.deps import Database, PlaceSettings

router = APIRouter(responses=ERROR_RESPONSES)
FRAME_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        "description": "An encoded frame structure (shared/frame.py, version 1).",
    }
}


INGEST_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/octet-stream": FRAME_BODY["requestBody"]["content"][
                "application/octet-stream"
            ],
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["frame"],
                    "properties": {
                        "frame": {"type": "string", "format": "binary"},
                        "rgb": {"type": "string", "format": "binary"},
                        "depth": {"type": "string", "format": "binary"},
                    },
                }
            },
        },
        "description": "An encoded frame structure, alone, or with its RGB-D view as "
        "multipart/form-data: `frame`, `rgb` (colour, JPEG) and `depth` (16-bit PNG, the "
        "frame's depth units); the frame must then carry its pose and intrinsics.",
    }
}
INGEST_TYPES = ("application/octet-stream", "multipart/form-data")
VIEW_FIELDS = ("frame", "rgb", "depth")


@router.get("/healthz", response_model=s.Health, response_model_exclude_none=True)
async def healthz(
    request: Request, db: Database, settings: PlaceSettings, caller: MaybeCaller
) -> s.Health:
    """Liveness; with a token (or in an open deployment) the database and index state (on
    a thread of its own: busy map routes never make it wait)."""
    loop = asyncio.get_running_loop()
    pool = request.app.state.health_pool
    host = (request.scope.get("server") or (None,))[0]  # the socket's address, not Host:
    return await loop.run_in_executor(pool, _health, db, settings, caller, host)


def _health(db: PlaceDB, settings, caller: str | None, host: str | None = None) -> s.Health:
    ok = db.ping()
    if caller is None:  # anonymous on a secured service: liveness only
        return s.Health(status="ok" if ok else "degraded")
    st = db.stats()
    healthy = ok and not st["storage_errors"] and not st["startup_warning"]
    return s.Health(
        status="ok" if healthy else "degraded",
        storage_errors=st["storage_errors"],
        worker_failures=st["worker_failures"],
        startup_warning=st["startup_warning"] or None,
        keyframes=st["keyframes"],
        robots=st["robots"],
        pending=st["pending"],
        database=st["db_path"],
        database_ok=ok,
        index_clusters=st["clusters"],
        index_cluster_max=st["cluster_max"],
        access_control=auth_summary(settings, host),  # as the start line says it
    )


@router.post(
    "/robots/{robot_id}/keyframes",
    status_code=201,
    response_model=s.KeyframeCreated,
    openapi_extra=INGEST_BODY,
    responses={200: {"model": s.KeyframeCreated}},
)
async def ingest(
    robot_id: str,
    request: Request,
    response: Response,
    db: Database,
    st: PlaceSettings,
    _writer: RobotWriter,  # the robot's own token or the operator's, before the body is read
) -> s.KeyframeCreated:
    """Store one keyframe's frame structure (and its RGB-D view, if sent) durably; 201 once
    it is on disk."""
    body = await read_body(request, st.max_body_bytes + st.max_view_bytes, INGEST_TYPES)
    view = None
    if body and request.headers.get("content-type", "").lower().startswith("multipart/"):
        body, view = await _keyframe_parts(request)
        size = sum(map(len, (view or {}).values()))
        if size > st.max_view_bytes:
            raise PayloadTooLarge(
                f"View of {size} bytes exceeds the {st.max_view_bytes}-byte limit"
            )
    if len(body) > st.max_body_bytes:
        raise PayloadTooLarge(f"Frame of {len(body)} bytes exceeds {st.max_body_bytes}")
    kf_id, created = await run_in_threadpool(db.add_keyframe, robot_id, body, view)
    if not created:
        response.status_code = 200
    info = db.keyframe_info(kf_id)
    return s.KeyframeCreated(id=kf_id, robot_id=robot_id, stamp=info["stamp"], created=created)


async def _keyframe_parts(request: Request) -> tuple[bytes, dict[str, bytes] | None]:
    """The frame and the view's images of a multipart keyframe."""
    # one more than we take, so a misnamed field gets its own message
    form = await request.form(max_files=len(VIEW_FIELDS) + 1, max_fields=len(VIEW_FIELDS) + 1)
    try:
        unknown = sorted(set(form.keys()) - set(VIEW_FIELDS))
        if unknown:
            raise BadInput(f"Unknown fields {unknown}: send {', '.join(VIEW_FIELDS)}")
        parts = {}
        for name in VIEW_FIELDS:
            part = form.get(name)
            if isinstance(part, str):
                raise BadInput(f"Field {name!r} must be a file part")
            if part is not None:
                parts[name] = await part.read()
    finally:
        await form.close()
    if "frame" not in parts:
        raise BadInput("Missing file field 'frame'")
    frame = parts.pop("frame")
    return frame, parts or None


@router.get("/robots", response_model=s.Robots, dependencies=[Depends(require_operator)])
def robots(db: Database) -> s.Robots:
    """The robots known, with keyframe counts."""
    return s.Robots(robots=[s.RobotInfo(**r) for r in db.robots()])


@router.get(
    "/robots/{robot_id}/keyframes",
    response_model=s.Keyframes,
    dependencies=[Depends(require_operator)],
)
def keyframes(
    robot_id: str,
    db: Database,
    offset: int = Query(0, ge=0, le=2**62),
    limit: int = Query(1000, ge=1, le=10000),
) -> s.Keyframes:
    """A robot's keyframes in time order, paged."""
    rows = db.keyframes(robot_id, offset, limit)
    return s.Keyframes(robot_id=robot_id, keyframes=[s.KeyframeInfo(**r) for r in rows])


@router.delete(
    "/robots/{robot_id}", response_model=s.Deleted, dependencies=[Depends(require_operator)]
)
def delete_robot(robot_id: str, db: Database) -> s.Deleted:
    """Delete a robot with its keyframes and overlaps."""
    return s.Deleted(robot_id=robot_id, deleted_keyframes=db.delete_robot(robot_id))


@router.get(
    "/keyframes/{kf_id}/frame",
    dependencies=[Depends(require_operator)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def keyframe_frame(db: Database, kf_id: int = Path(ge=1, le=2**63 - 1)) -> Response:
    """The stored encoded frame of one keyframe."""
    return Response(db.frame_bytes(kf_id), media_type="application/octet-stream")


def _winner(db: PlaceDB, c: Candidate) -> s.Winner:
    return s.Winner(
        keyframe_id=c.kf_id,
        robot_id=db.robot_name(c.robot_code),
        stamp=c.stamp,
        inliers=c.verification.inliers,
        matches=c.verification.matches,
        gist_distance=c.gist_distance,
        bow_distance=c.bow_distance,
    )


@router.post(
    "/query",
    response_model=s.QueryAnswer,
    openapi_extra=FRAME_BODY,
    dependencies=[Depends(require_token)],
)
async def query(
    request: Request,
    db: Database,
    st: PlaceSettings,
    robot: str | None = None,
    exclude_robot: str | None = None,
    max_stamp: float | None = Query(None, allow_inf_nan=False),
) -> s.QueryAnswer:
    """The retrieval cascade's answer for one frame: winner, verified list, stage counts."""
    body = await read_body(request, st.max_body_bytes, ("application/octet-stream",))
    frame = decode(body)
    flt = db.make_filter(robot, exclude_robot, max_stamp)
    r = await run_in_threadpool(db.query, frame, flt)
    verified = [_winner(db, c) for c in r.verified if db.robot_name(c.robot_code) is not None]
    return s.QueryAnswer(
        # a candidate whose robot was deleted while the query ran is left out
        winner=next(iter(verified), None),
        verified=verified,
        stages=[s.StageInfo(name=x.name, kept=x.kept, ms=x.ms) for x in r.stages],
        database_size=r.database_size,
        total_ms=r.total_ms,
    )


@router.get(
    "/overlaps",
    response_model=s.Overlaps,
    response_model_exclude_none=True,
    dependencies=[Depends(require_operator)],
)
async def overlaps(
    db: Database,
    st: PlaceSettings,
    robot_a: str | None = None,
    robot_b: str | None = None,
    wait: float = Query(0.0, ge=0.0, le=600.0, allow_inf_nan=False),
    source: Literal["all", "cascade", "link", "nominated"] = "all",
) -> s.Overlaps:
    """Verified keyframe pairs between two robots, or without robots the overlap graph.
    `wait` seconds at most for keyframes still queued for overlap detection (an async wait:
    it holds no worker thread); `source` keeps only the cascade's pairs or only those
    co-visible under a registered link; "nominated": not overlaps but where to align when
    none is verified (the BoW-nearest keyframe pairs, computed on request). With
    `defer_overlaps` the first request starts the detection of every keyframe queued."""
    if st.defer_overlaps:
        db.start_detection()
    end = time.monotonic() + wait
    while db.pending() and time.monotonic() < end:
        await asyncio.sleep(0.05)
    return await run_in_threadpool(_overlaps, db, robot_a, robot_b, source)


def _overlaps(db: PlaceDB, robot_a, robot_b, source) -> s.Overlaps:
    if robot_a is None and robot_b is None:
        return s.Overlaps(
            graph=[s.OverlapEdge(**e) for e in db.overlap_graph()], pending=db.pending()
        )
    if robot_a is None or robot_b is None:
        raise BadInput("Give both robot_a and robot_b, or neither for the overlap graph")
    pairs = [
        s.OverlapPair(
            robot_a=o.robot_a,
            keyframe_a=o.kf_a,
            stamp_a=o.stamp_a,
            robot_b=o.robot_b,
            keyframe_b=o.kf_b,
            stamp_b=o.stamp_b,
            inliers=o.inliers,
            matches=o.matches,
            source=o.source,
        )
        for o in (
            nominated_overlaps(db, robot_a, robot_b)
            if source == "nominated"
            else db.overlaps(robot_a, robot_b)
        )
        if source in ("all", o.source)
    ]
    return s.Overlaps(overlaps=pairs, pending=db.pending())


@router.put(
    "/links/{robot_a}/{robot_b}",
    response_model=s.LinkOut,
    dependencies=[Depends(require_operator)],
)
async def put_link(robot_a: str, robot_b: str, body: s.LinkIn, db: Database) -> s.LinkOut:
    """Register the alignment of two robots' maps (from the aligner, after its quality
    gate); the keyframe pairs co-visible under it become overlaps with source "link"."""
    n = await run_in_threadpool(db.add_link, robot_a, robot_b, np.array(body.transform, np.float64))
    return s.LinkOut(robot_a=robot_a, robot_b=robot_b, link_overlaps=n)


@router.get("/links", response_model=list[s.Link], dependencies=[Depends(require_operator)])
def links(db: Database) -> list[s.Link]:
    """The registered map alignments."""
    return [s.Link(**x) for x in db.links()]


@router.get("/vocabulary", dependencies=[Depends(require_token)])
def vocabulary(db: Database) -> dict:
    """The vocabulary frames must be built with."""
    v = db.vocabulary
    return {
        "vocab_id": v.vocab_id,
        "words": v.n_words,
        "gist_dim": v.gist_params.dim,
        "gist_clusters": len(v.gist_centroids),
        "source": v.source,
    }


@router.get("/stats", dependencies=[Depends(require_operator)])
def stats(db: Database) -> dict:
    """Database and index statistics (cluster balance, pending work, sizes)."""
    return db.stats()


@router.get("/config", response_model=s.CONFIG.model, dependencies=[Depends(require_operator)])
def config(settings: PlaceSettings):
    """The parameters in force: the settings as resolved from their defaults and the
    `FLEETMAP_PLACE_DB_*` variables (the cascade's, the live map's...), nested as they are;
    tokens left out, the database's and the aligner's URLs without their passwords."""
    return s.CONFIG.answer(settings)


@router.post("/admin/retrain", response_model=s.Retrained, dependencies=[Depends(require_operator)])
def retrain(db: Database, clusters: int | None = Query(None, ge=2, le=65536)) -> s.Retrained:
    """Retrain the coarse GIST codebook from the stored keyframes; no downtime."""
    return s.Retrained(**db.retrain(clusters))
