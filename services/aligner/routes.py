"""Aligner routes: parse the multipart request, call the core, answer a schema."""

from __future__ import annotations

import json
import uuid

import numpy as np
from fastapi import APIRouter, Depends, Request, Response
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from fleetmap.align import merged_cloud, method
from fleetmap.align.types import AlignParams
from fleetmap.camera import Intrinsics
from fleetmap.correspondences import RGBDView
from fleetmap.errors import BadInput, PayloadTooLarge, UnknownCloud
from fleetmap.services.aligner import schemas as s
from fleetmap.services.aligner.deps import AlignerSettings, Budget, Clouds
from fleetmap.services.auth import require_token
from fleetmap.services.body import read_body
from fleetmap.services.http_errors import ERROR_RESPONSES
from fleetmap.view import check_intrinsics, decode_image, image_size
from fleetmap.wire import ALIGN_META, view_part

router = APIRouter(responses=ERROR_RESPONSES)
FORM_TYPES = ("multipart/form-data", "application/x-www-form-urlencoded")


@router.get("/healthz", response_model=s.Health)
def healthz(clouds: Clouds) -> s.Health:
    """Liveness and the merged clouds held for download."""
    return s.Health(status="ok", clouds_cached=len(clouds))


@router.get("/config", response_model=s.CONFIG.model, dependencies=[Depends(require_token)])
def config(settings: AlignerSettings):
    """The parameters in force: the settings as resolved from their defaults and the
    `FLEETMAP_ALIGNER_*` variables (the alignment's gate and ICP, the limits), nested as
    they are; tokens left out."""
    return s.CONFIG.answer(settings)


def align_answer(
    pairs, name: str, p: AlignParams, want_cloud: bool, colour: str
) -> tuple[dict, tuple[bytes, int] | None]:
    """One request's answer: the result's fields, and the merged cloud as PLY bytes with
    its point count when asked for and merged."""
    from fleetmap.mapcloud import ply_bytes

    res = method(name)(pairs, p)
    cloud = None
    if want_cloud and res.merged:
        pts, cols = merged_cloud(pairs, res, colour, p.voxel_m)
        cloud = (ply_bytes(pts, cols), len(pts))
    return res.to_dict(), cloud


def _view(files: dict[str, bytes], name: str, vm: s.ViewMeta) -> RGBDView:
    rgb_part, depth_part = (
        view_part(name[0], int(name[1:]), "rgb"),
        view_part(name[0], int(name[1:]), "depth"),
    )
    rgb = decode_image(files[rgb_part], rgb_part, False)
    depth = decode_image(files[depth_part], depth_part, True)
    try:
        intrinsics = Intrinsics(**vm.intrinsics.model_dump())
        check_intrinsics(intrinsics, rgb.shape[1], rgb.shape[0], "intrinsics")
        return RGBDView(rgb, depth, intrinsics, np.array(vm.T_map_cam), vm.stamp)
    except BadInput as exc:
        raise BadInput(f"view {name}: {exc}") from exc


def _views(files: dict[str, bytes], meta: s.AlignMeta) -> list[tuple[RGBDView, RGBDView]]:
    """Decode every view (in a worker thread: decoding is heavy)."""
    if meta.views_a:  # indexed layout: each view once
        va = [_view(files, f"a{i}", vm) for i, vm in enumerate(meta.views_a)]
        vb = [_view(files, f"b{j}", vm) for j, vm in enumerate(meta.views_b)]
        return [(va[i], vb[j]) for i, j in meta.pairs]
    return [
        (_view(files, f"a{i}", pm.a), _view(files, f"b{i}", pm.b))
        for i, pm in enumerate(meta.pairs)
    ]


def _view_names(meta: s.AlignMeta) -> list[str]:
    if meta.views_a:
        names = [f"a{i}" for i in range(len(meta.views_a))]
        return names + [f"b{j}" for j in range(len(meta.views_b))]
    return [f"{side}{i}" for i in range(len(meta.pairs)) for side in "ab"]


def _parse_meta(raw) -> s.AlignMeta:
    if not isinstance(raw, str):
        raise BadInput("Missing 'meta' field (JSON)")
    try:
        return s.AlignMeta.model_validate(json.loads(raw))
    except RecursionError as exc:
        raise BadInput("Bad 'meta' field: JSON nested too deep") from exc
    except (ValidationError, ValueError, TypeError) as exc:  # ValueError: also huge integers
        raise BadInput(f"Bad 'meta' field: {str(exc)[:500]}") from exc


async def _files(form, names: list[str], max_pixels: int) -> tuple[dict[str, bytes], int]:
    """Each view's two files, checked against the pixel limit from their headers; returns
    them with the pixels they will take decoded."""
    files, total = {}, 0
    for n in names:
        for kind in ("rgb", "depth"):
            key = f"{n}_{kind}"
            part = form.get(key)
            if part is None or isinstance(part, str):
                raise BadInput(f"Missing file field {key!r}")
            data = await part.read()
            w, h = image_size(data, key)
            if w * h > max_pixels:
                raise PayloadTooLarge(f"{key}: {w}x{h} exceeds the pixel limit of {max_pixels}")
            files[key], total = data, total + w * h
    return files, total


ALIGN_BODY = {
    "requestBody": {
        "required": True,
        "description": "multipart/form-data: `meta` (AlignMeta as JSON) and, per view, "
        "`a{i}_rgb`, `a{i}_depth` (robot A's view i) and `b{j}_rgb`, `b{j}_depth` (robot B's "
        "view j): colour in any format OpenCV reads (PNG recommended), depth as 16-bit "
        "single-channel PNG, metres = value / depth_scale. See services/aligner/schemas.py.",
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": [ALIGN_META],
                    "properties": {
                        ALIGN_META: {"type": "string", "description": "AlignMeta as JSON"},
                        "a0_rgb": {"type": "string", "format": "binary"},
                        "a0_depth": {"type": "string", "format": "binary"},
                        "b0_rgb": {"type": "string", "format": "binary"},
                        "b0_depth": {"type": "string", "format": "binary"},
                    },
                    "additionalProperties": {"type": "string", "format": "binary"},
                },
                "encoding": {ALIGN_META: {"contentType": "application/json"}},
            }
        },
    }
}


@router.post(
    "/align",
    response_model=s.AlignAnswer,
    response_model_exclude_none=True,
    dependencies=[Depends(require_token)],
    openapi_extra=ALIGN_BODY,
)
async def align(
    request: Request, st: AlignerSettings, budget: Budget, clouds: Clouds
) -> s.AlignAnswer:
    """Fit the transform from robot B's map frame into robot A's from RGB-D pairs."""
    async with budget.slot():  # before the body: requests that wait hold no memory
        # chunked or not, cut off at the limit
        await read_body(request, st.max_body_bytes, FORM_TYPES)
        try:
            form = await request.form(max_files=4 * st.max_views, max_fields=8)
        except StarletteHTTPException as exc:  # its limit tripped before the views are counted
            if "files" not in str(exc.detail):
                raise
            raise BadInput(
                f"At most {st.max_views} views per robot ({4 * st.max_views} image files): "
                "send fewer (fleetmap's --max-views)"
            ) from None
        meta = _parse_meta(form.get(ALIGN_META))
        if len(meta.pairs) > st.max_pairs:
            raise BadInput(f"At most {st.max_pairs} pairs, got {len(meta.pairs)}")
        n_views = max(len(meta.views_a), len(meta.views_b)) or len(meta.pairs)
        if n_views > st.max_views:
            raise BadInput(f"At most {st.max_views} views per robot, got {n_views}")
        files, pixels = await _files(form, _view_names(meta), st.max_image_pixels)
        await form.close()
        del form
        request._body = b""  # the parts are in `files` now
        async with budget.hold(pixels):
            pairs = await run_in_threadpool(_views, files, meta)
            del files
            result, cloud = await run_in_threadpool(
                align_answer, pairs, meta.method, st.align, meta.cloud, meta.colour
            )
    answer = s.AlignAnswer(**result)
    if cloud is not None:
        cid = uuid.uuid4().hex[:12]
        clouds[cid] = cloud
        while len(clouds) > st.cloud_cache:
            clouds.pop(next(iter(clouds)))
        answer.cloud_id, answer.cloud_points = cid, cloud[1]
    return answer


@router.get(
    "/clouds/{cloud_id}",
    dependencies=[Depends(require_token)],
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def cloud(cloud_id: str, clouds: Clouds) -> Response:
    """The merged cloud of an alignment as a binary PLY."""
    item = clouds.get(cloud_id)
    if item is None:
        raise UnknownCloud(f"Unknown cloud {cloud_id!r}")
    return Response(
        item[0],
        media_type="application/octet-stream",
        headers={"content-disposition": f'attachment; filename="{cloud_id}.ply"'},
    )
