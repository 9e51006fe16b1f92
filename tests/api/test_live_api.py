"""Keyframes with their RGB-D views, and the live map, over HTTP (in-process TestClient) on
both backends; the merge worker driven step by step with the real alignment pipeline."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.align import align_views
from fleetmap.dataset import read_recording
from fleetmap.extract import FrameExtractor, keyframe_indices
from fleetmap.fleet.merge_worker import LiveMap, LiveParams
from fleetmap.fleet.view_choice import load_view
from fleetmap.frame import encode
from fleetmap.geometry import transform_error
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from fleetmap.view import encode_view

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


@pytest.fixture(scope="module")
def keyframes(vocabulary):
    """{robot: [(encoded frame, view)]} of the bundled TUM fr1 pair."""
    x, out = FrameExtractor(vocabulary), {}
    for robot in ("alpha", "bravo"):
        rec = read_recording(EXAMPLE / robot)
        out[robot] = []
        for i in keyframe_indices(rec):
            v = load_view(rec, i)
            frame = x(robot, v.stamp, v.rgb, v.depth, rec.intrinsics, v.T_map_cam)
            out[robot].append((encode(frame), encode_view(v.rgb, v.depth)))
    return out


@pytest.fixture(params=["sqlite", "postgres"])
def settings(request, tmp_path):
    database = request.getfixturevalue("pg_url") if request.param == "postgres" else None
    return Settings(data_dir=tmp_path, database=database, max_view_bytes=2_000_000)


def post(client, robot: str, frame: bytes, view: dict | None = None, extra: dict | None = None):
    files = {"frame": ("frame", frame, "application/octet-stream")}
    for k, v in (view or {}).items():
        files[k] = (k, v, "application/octet-stream")
    return client.post(f"/robots/{robot}/keyframes", files=files | (extra or {}))


def test_a_view_is_stored_with_its_keyframe(settings, keyframes):
    frame, view = keyframes["alpha"][0]
    with TestClient(create_app(settings)) as client:
        r = post(client, "alpha", frame, view)
        assert r.status_code == 201, r.text
        kf = r.json()["id"]
        assert post(client, "alpha", frame, view).status_code == 200  # idempotent
        got = client.get(f"/keyframes/{kf}/view").json()
        assert got["robot_id"] == "alpha" and (got["width"], got["height"]) == (640, 480)
        assert client.get(f"/keyframes/{kf}/view/rgb").content == view["rgb"]
        assert client.get(f"/keyframes/{kf}/view/depth").content == view["depth"]
        plain = post(client, "bravo", keyframes["bravo"][0][0])  # a frame alone, multipart
        assert plain.status_code == 201
        missing = client.get(f"/keyframes/{plain.json()['id']}/view")
        assert missing.status_code == 404 and "without its RGB-D view" in missing.json()["detail"]
        assert client.get("/keyframes/999999/view").status_code == 404


def _png(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


BAD_VIEWS = {
    "no depth": (lambda v: {"rgb": v["rgb"]}, 422, "missing ['depth']"),
    "8-bit depth": (
        lambda v: v | {"depth": _png(np.full((480, 640), 9, np.uint8))},
        422,
        "16-bit",
    ),
    "wrong size": (lambda v: v | {"rgb": _png(np.zeros((240, 320, 3), np.uint8))}, 422, "320x240"),
    "not an image": (lambda v: v | {"depth": b"\x89PNG not really"}, 422, "depth"),
    "no reading": (lambda v: v | {"depth": _png(np.zeros((480, 640), np.uint16))}, 422, "no valid"),
    "too large": (lambda v: v | {"rgb": b"\xff\xd8" + bytes(2_100_000)}, 413, "limit"),
}


@pytest.mark.parametrize("case", list(BAD_VIEWS))
def test_bad_views_answer_4xx_and_store_nothing(settings, keyframes, case):
    frame, view = keyframes["alpha"][0]
    change, status, msg = BAD_VIEWS[case]
    with TestClient(create_app(settings)) as client:
        r = post(client, "alpha", frame, change(view))
        assert r.status_code == status and msg in r.json()["detail"], r.text
        assert client.get("/robots").json()["robots"] == []
        extra = {"colour": ("c", view["rgb"], "image/jpeg")}
        r = post(client, "alpha", frame, view, extra)
        assert r.status_code == 422 and "Unknown fields ['colour']" in r.json()["detail"]
        assert post(client, "alpha", frame, view).status_code == 201  # the good one still goes


def test_the_merge_worker_places_the_pair_and_every_replica_serves_it(settings, keyframes):
    """The worker (run step by step, with the aligner's real pipeline in-process) merges the
    pair on its verified overlap; the map is within 5 cm / 2 deg of the truth, the same on a
    second service over the same database; nothing is aligned again without new overlaps."""
    app = create_app(settings)
    with TestClient(app) as client:
        for robot, kfs in keyframes.items():
            for frame, view in kfs:
                assert post(client, robot, frame, view).status_code == 201
        assert client.get("/overlaps", params={"wait": 60}).json()["graph"]
        calls = []

        def align(pairs):
            calls.append(len(pairs))
            views = {id(v): v.decoded() for pair in pairs for v in pair}  # each view once
            pairs = [(views[id(x)], views[id(y)]) for x, y in pairs]
            return align_views(pairs).to_dict()

        never_quiet = LiveParams(settle_s=3600)  # no last fit: one alignment exactly
        live = LiveMap(app.state.db, align, never_quiet)
        assert live.tick() is True and live.tick() is False and len(calls) == 1
        m = client.get("/map").json()
        assert m["reference"] == "alpha" and m["unmerged"] == [] and m["version"] >= 1
        dt, dr = transform_error(
            np.array(m["transforms"]["bravo"]), np.loadtxt(EXAMPLE / "T_alpha_bravo.txt")
        )
        assert dt < 0.05 and dr < 2.0, (dt, dr)
        png = client.get("/map/overview.png")
        assert png.headers["content-type"] == "image/png" and len(png.content) > 10_000
        ply = client.get("/map/cloud.ply", params={"voxel": 0.1}).content
        assert int(ply.split(b"element vertex ")[1].split()[0]) > 500
        assert client.get("/map/cloud.ply", params={"voxel": 0}).status_code == 422
    with TestClient(create_app(settings)) as other:  # a restart, or a second replica
        again = other.get("/map").json()
        assert again["transforms"] == m["transforms"] and again["version"] == m["version"]
        assert LiveMap(other.app.state.db, align, never_quiet).tick() is False
        assert len(calls) == 1
