"""Views bounded by their decoding cost and checked against their intrinsics, on ingest
(both backends) and on /align alike (issue 26.4, 26.5, 26.12)."""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import cv2
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from fleetmap.client import align_request
from fleetmap.dataset import read_recording
from fleetmap.extract import FrameExtractor
from fleetmap.fleet.view_choice import load_view
from fleetmap.frame import encode
from fleetmap.services.aligner.config import Settings as AlignerSettings
from fleetmap.services.aligner.main import create_app as aligner_app
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from fleetmap.view import MAX_JPEG_SCANS, encode_view, jpeg_scans

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


def scan_bomb(width: int, height: int, repeats: int) -> bytes:
    """A flat progressive JPEG whose last (AC refinement) scan is repeated: a few bytes per
    scan, and the decoder passes over every block once per scan."""
    buf = io.BytesIO()
    Image.new("RGB", (width, height), (128, 128, 128)).save(buf, "JPEG", progressive=True)
    jpeg = buf.getvalue()
    last = jpeg.rindex(b"\xff\xda")
    end = jpeg.rindex(b"\xff\xd9")
    return jpeg[:end] + jpeg[last:end] * repeats + jpeg[end:]


@pytest.fixture(scope="module")
def alpha(vocabulary):
    """The bundled robot alpha's first keyframe: (recording, view, extractor)."""
    rec = read_recording(EXAMPLE / "alpha")
    return rec, load_view(rec, 0), FrameExtractor(vocabulary)


def keyframe(alpha, intrinsics=None, size=None) -> tuple[bytes, dict]:
    rec, v, x = alpha
    k = intrinsics or rec.intrinsics
    rgb, depth = v.rgb, v.depth
    if size is not None:
        rgb = cv2.resize(rgb, size)
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
    frame = x("alpha", v.stamp, rgb, depth, k, v.T_map_cam)
    return encode(frame), encode_view(rgb, depth)


@pytest.fixture(params=["sqlite", "postgres"])
def client(request, tmp_path):
    database = request.getfixturevalue("pg_url") if request.param == "postgres" else None
    settings = Settings(data_dir=tmp_path, database=database, max_view_bytes=16 * 2**20)
    with TestClient(create_app(settings)) as c:
        yield c


def post(client, frame: bytes, view: dict):
    files = {"frame": ("frame", frame, "application/octet-stream")}
    files |= {k: (k, v, "application/octet-stream") for k, v in view.items()}
    return client.post("/robots/alpha/keyframes", files=files)


def test_a_scan_bomb_is_refused_before_decoding(client, alpha):
    frame, view = keyframe(alpha)
    bomb = scan_bomb(640, 480, 3000)  # 40 kB; about 1 s to decode on this machine
    assert jpeg_scans(bomb) > MAX_JPEG_SCANS
    r = post(client, frame, view | {"rgb": bomb})
    assert r.status_code == 413 and "scans" in r.json()["detail"], r.text
    progressive = scan_bomb(640, 480, 0)  # a plain progressive JPEG (10 scans) still goes
    assert post(client, frame, view | {"rgb": progressive}).status_code == 201


@pytest.mark.parametrize(
    "case",
    [
        "focal 1e-9",
        "640x480 intrinsics on 1280x960",
    ],
)
def test_implausible_intrinsics_are_refused(client, alpha, case):
    rec = alpha[0]
    if case == "focal 1e-9":
        frame, view = keyframe(alpha, replace(rec.intrinsics, fx=1e-9, fy=1e-9))
    else:
        big = replace(rec.intrinsics, width=1280, height=960)
        frame, view = keyframe(alpha, big, (1280, 960))
    r = post(client, frame, view)
    assert r.status_code == 422 and "intrinsics implausible" in r.json()["detail"], r.text
    assert client.get("/robots").json()["robots"] == []


def test_align_refuses_scan_bombs_and_implausible_intrinsics(tum_two_robots):
    pairs, _ = tum_two_robots
    with TestClient(aligner_app(AlignerSettings(max_body_bytes=20_000_000))) as c:
        req = align_request(pairs)
        req["files"]["a0_rgb"] = ("a.jpg", scan_bomb(640, 480, 3000))
        r = c.post("/align", **req)
        assert r.status_code == 413 and "scans" in r.json()["detail"], r.text
        a, b = pairs[0]
        tiny = replace(a, intrinsics=replace(a.intrinsics, fx=1e-9, fy=1e-9))
        r = c.post("/align", **align_request([(tiny, b)]))
        assert r.status_code == 422 and "intrinsics implausible" in r.json()["detail"], r.text


def test_more_views_than_the_aligner_takes_are_named_with_its_limit(tum_two_robots):
    """`fleetmap merge --max-views 40` ended "/align: Too many files. Maximum number of files
    is 128." (an outside tester's review): the form's file limit tripped before the views
    were counted. The answer names the views' limit and the flag; fewer views still align."""
    pairs, _ = tum_two_robots
    with TestClient(aligner_app(AlignerSettings(max_body_bytes=20_000_000, max_views=1))) as c:
        a, b = pairs[0]
        r = c.post("/align", **align_request([(a, b), (replace(a), replace(b))]))  # 2 views
        assert r.status_code == 422, r.text
        assert r.json()["detail"].startswith("At most 1 views per robot (4 image files)"), r.text
        assert "--max-views" in r.json()["detail"]
        assert c.post("/align", **align_request(pairs[:1])).status_code == 200


@pytest.mark.parametrize("depth_scale", [1e-9, 0.001, 1e300])
def test_align_refuses_a_depth_scale_no_camera_has(tum_two_robots, depth_scale):
    """An outside tester's /align with depth_scale 1e-9 answered 500 ("Maximum allowed size
    exceeded", the clouds' reach at 1e9 m), and 1e300 kept a worker busy past 8 minutes,
    every other request 503: now 422 before anything is decoded (`camera.DEPTH_SCALE_RANGE`);
    0.001 is RealSense's metres per unit, 1000 here."""
    import json

    pairs, _ = tum_two_robots
    req = align_request(pairs[:1])
    (key,) = req["data"]
    meta = json.loads(req["data"][key])
    meta["views_a"][0]["intrinsics"]["depth_scale"] = depth_scale
    req["data"][key] = json.dumps(meta)
    with TestClient(aligner_app(AlignerSettings(max_body_bytes=20_000_000))) as c:
        r = c.post("/align", **req)
        assert r.status_code == 422 and "depth_scale" in r.text, r.text
        assert c.post("/align", **align_request(pairs[:1])).status_code == 200


def test_a_depth_image_in_the_colour_part_is_refused(client, alpha):
    """A 16-bit depth PNG sent as `rgb` was squeezed to 8 bits and stored as the view's
    colour (201; an outside tester's review)."""
    frame, view = keyframe(alpha)
    r = post(client, frame, view | {"rgb": view["depth"]})
    assert r.status_code == 422 and "colour must be 8-bit" in r.json()["detail"], r.text
    assert client.get("/robots").json()["robots"] == []
