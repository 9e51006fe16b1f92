"""Aligner routes: parse the multipart request, call the core, answer a schema."""

from __future__ import annotations

import json
import uuid

import cv2
import numpy as np
from fastapi import APIRouter, Depends, Request, Response
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from services.aligner import schemas as s
from services.common import any_token
from shared.align import align_request
from shared.camera import Intrinsics
from shared.correspondences import RGBDView
from shared.errors import BadInput, PayloadTooLarge, UnknownKeyframe

router = APIRouter()


@router.get("/healthz", response_model=s.Health)
def healthz(request: Request) -> s.Health:
    """Liveness and the merged clouds held for download."""
    return s.Health(status="ok", clouds_cached=len(request.app.state.clouds))


async def _decode(form, name: str, depth: bool, max_pixels: int) -> np.ndarray:
    part = form.get(name)
    if part is None or isinstance(part, str):
        raise BadInput(f"Missing file field {name!r}")
    data = await part.read()
    buf = np.frombuffer(data, np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED if depth else cv2.IMREAD_COLOR)
    if img is None:
        raise BadInput(f"{name}: image does not decode")
    if img.shape[0] * img.shape[1] > max_pixels:
        raise PayloadTooLarge(f"{name}: {img.shape[1]}x{img.shape[0]} exceeds the pixel limit")
    if depth and (img.dtype != np.uint16 or img.ndim != 2):
        raise BadInput(f"{name}: depth must be 16-bit single channel, got {img.dtype} {img.shape}")
    return img


async def _view(form, name: str, vm: s.ViewMeta, max_pixels: int) -> RGBDView:
    rgb = await _decode(form, f"{name}_rgb", False, max_pixels)
    depth = await _decode(form, f"{name}_depth", True, max_pixels)
    try:
        return RGBDView(
            rgb, depth, Intrinsics(**vm.intrinsics.model_dump()), np.array(vm.T_map_cam), vm.stamp
        )
    except BadInput as exc:
        raise BadInput(f"view {name}: {exc}") from exc


async def _views(form, meta: s.AlignMeta, max_pixels: int) -> list[tuple[RGBDView, RGBDView]]:
    if meta.views_a:  # indexed layout: each view once
        va = [await _view(form, f"a{i}", vm, max_pixels) for i, vm in enumerate(meta.views_a)]
        vb = [await _view(form, f"b{j}", vm, max_pixels) for j, vm in enumerate(meta.views_b)]
        return [(va[i], vb[j]) for i, j in meta.pairs]
    return [
        (
            await _view(form, f"a{i}", pm.a, max_pixels),
            await _view(form, f"b{i}", pm.b, max_pixels),
        )
        for i, pm in enumerate(meta.pairs)
    ]


@router.post(
    "/align",
    response_model=s.AlignAnswer,
    response_model_exclude_none=True,
    dependencies=[Depends(any_token)],
)
async def align(request: Request) -> s.AlignAnswer:
    """Fit the transform from robot B's map frame into robot A's from RGB-D pairs."""
    st = request.app.state.settings
    declared = int(request.headers.get("content-length") or 0)
    if declared > st.max_body_bytes:
        raise PayloadTooLarge(
            f"Body of {declared} bytes exceeds the {st.max_body_bytes}-byte limit"
        )
    form = await request.form(max_files=4 * st.max_views, max_fields=8)
    try:
        meta = s.AlignMeta.model_validate(json.loads(form.get("meta") or "null"))
    except (ValidationError, json.JSONDecodeError, TypeError) as exc:
        raise BadInput(f"Bad 'meta' field: {exc}") from exc
    if len(meta.pairs) > st.max_pairs:
        raise BadInput(f"At most {st.max_pairs} pairs, got {len(meta.pairs)}")
    n_views = max(len(meta.views_a), len(meta.views_b)) or len(meta.pairs)
    if n_views > st.max_views:
        raise BadInput(f"At most {st.max_views} views per robot, got {n_views}")
    pairs = await _views(form, meta, st.max_image_pixels)
    result, cloud = await run_in_threadpool(
        align_request, pairs, meta.method, st.params(), meta.cloud, meta.colour
    )
    answer = s.AlignAnswer(**result)
    if cloud is not None:
        cid = uuid.uuid4().hex[:12]
        clouds = request.app.state.clouds
        clouds[cid] = cloud
        while len(clouds) > st.cloud_cache:
            clouds.pop(next(iter(clouds)))
        answer.cloud_id, answer.cloud_points = cid, cloud[1]
    return answer


@router.get(
    "/clouds/{cloud_id}",
    dependencies=[Depends(any_token)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def cloud(cloud_id: str, request: Request) -> Response:
    """The merged cloud of an alignment as a binary PLY."""
    item = request.app.state.clouds.get(cloud_id)
    if item is None:
        raise UnknownKeyframe(f"Unknown cloud {cloud_id!r}")
    return Response(
        item[0],
        media_type="application/octet-stream",
        headers={"content-disposition": f'attachment; filename="{cloud_id}.ply"'},
    )
