"""The aligner over HTTP (in-process TestClient)."""

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.client import align_request
from fleetmap.geometry import transform_error
from fleetmap.services.aligner.config import Settings
from fleetmap.services.aligner.main import create_app


@pytest.fixture
def client():
    with TestClient(create_app(Settings(max_body_bytes=20_000_000))) as c:
        yield c


def _request(pairs, **meta_kw):
    return align_request(pairs, **meta_kw)


def _post_with_file(client, pairs, field: str, data: bytes):
    """/align with one image file replaced by `data`."""
    req = _request(pairs)
    req["files"][field] = ("x.png", data)
    return client.post("/align", **req)


def test_align_returns_the_transform_and_a_merged_ply(client, tum_two_robots):
    pairs, T_a_b = tum_two_robots
    r = client.post("/align", **_request(pairs, cloud=True))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["merged"] and body["method"].startswith("rigid")
    dt, dr = transform_error(np.array(body["transform"]), T_a_b)
    assert dt < 0.05 and dr < 2.0
    ply = client.get(f"/clouds/{body['cloud_id']}")
    assert ply.status_code == 200 and ply.content.startswith(b"ply")
    assert b"binary_little_endian" in ply.content[:200]


@pytest.mark.parametrize("method", ["rigid", "affine", "mlp"])
def test_baseline_methods(client, tum_two_robots, method):
    pairs, T_a_b = tum_two_robots
    body = client.post("/align", **_request(pairs, method=method)).json()
    assert body["method"] == method
    if method != "mlp":
        assert transform_error(np.array(body["transform"]), T_a_b)[0] < 0.1


def test_bad_requests_answer_4xx(client, tum_two_robots):
    pairs, _ = tum_two_robots
    req = _request(pairs)
    del req["files"]["b0_depth"]
    r = client.post("/align", **req)
    assert r.status_code == 422 and "b0_depth" in r.json()["detail"]

    r = _post_with_file(client, pairs, "a0_rgb", b"not an image")
    assert r.status_code == 422 and "not an image" in r.json()["detail"]

    a, b = pairs[0]
    r = _post_with_file(client, pairs, "a0_depth", cv2.imencode(".png", a.depth[:100])[1].tobytes())
    assert r.status_code == 422 and "does not match colour" in r.json()["detail"]

    empty_depth = cv2.imencode(".png", np.zeros_like(b.depth))[1].tobytes()
    r = _post_with_file(client, pairs, "b0_depth", empty_depth)
    assert "no valid reading" in r.json()["detail"]

    req = _request(pairs)
    req["data"]["meta"] = "{broken"
    assert client.post("/align", **req).status_code == 422
    req = _request(pairs)
    meta = json.loads(req["data"]["meta"])
    meta["views_a"][0]["T_map_cam"] = [[1, 0], [0, 1]]
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 422 and "4x4" in r.json()["detail"]
    # index pairs pointing outside the views, or without views
    meta = json.loads(_request(pairs)["data"]["meta"])
    meta["pairs"] = [[0, 7]]
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 422 and "outside views_a (1) or views_b (1)" in r.json()["detail"]
    meta["views_a"] = meta["views_b"] = []
    meta["pairs"] = [[0, 0]]
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 422 and "need views_a and views_b" in r.json()["detail"]


def test_inline_pair_layout_still_accepted(client, tum_two_robots):
    """Pairs carrying their own view metadata, files per pair (the first layout)."""
    pairs, T_true = tum_two_robots
    req = _request(pairs)
    meta = json.loads(req["data"]["meta"])
    meta["pairs"] = [{"a": meta["views_a"][i], "b": meta["views_b"][j]} for i, j in meta["pairs"]]
    del meta["views_a"], meta["views_b"]
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 200, r.text
    dt, dr = transform_error(np.array(r.json()["transform"]), T_true)
    assert dt < 0.05 and dr < 2.0
    gone = client.get("/clouds/nope")
    assert gone.status_code == 404 and gone.json()["error"] == "UnknownCloud"  # not a keyframe


def test_oversized_body_is_refused(tum_two_robots):
    pairs, _ = tum_two_robots
    with TestClient(create_app(Settings(max_body_bytes=1000))) as c:
        r = c.post("/align", **_request(pairs))
        assert r.status_code == 413


def _png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height, with almost no pixel data: a 2.6 MB
    file like this made the aligner allocate 5.7 GB before its 413 (issue 15)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\0" * 1000)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_hostile_align_requests_answer_4xx_before_spending_memory(client, tum_two_robots):
    """Issue 15's attacks on /align, each a 500 or a multi-GB allocation before."""
    pairs, _ = tum_two_robots
    r = _post_with_file(client, pairs, "a0_rgb", _png_declaring(30000, 30000))
    assert r.status_code == 413 and "a0_rgb" in r.json()["detail"]

    r = _post_with_file(client, pairs, "b0_depth", b"")
    assert r.status_code == 422 and "b0_depth: empty file" in r.json()["detail"]

    for meta in ("[" * 100_000 + "]" * 100_000, '{"pairs": ' + "9" * 5000 + "}"):
        req = _request(pairs)
        req["data"]["meta"] = meta
        r = client.post("/align", **req)
        assert r.status_code == 422 and "Bad 'meta' field" in r.json()["detail"], r.text

    req = _request(pairs)
    meta = json.loads(req["data"]["meta"])
    meta["views_b"][0]["T_map_cam"] = [[0.0] * 4 for _ in range(4)]
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 422 and "bottom row" in r.json()["detail"]

    meta = json.loads(_request(pairs)["data"]["meta"])
    meta["views_a"][0]["stamp"] = float("nan")  # 200 before (an outside tester's review)
    req["data"]["meta"] = json.dumps(meta)
    r = client.post("/align", **req)
    assert r.status_code == 422 and "stamp" in r.json()["detail"], r.text


def test_chunked_body_is_cut_off_at_the_limit(tum_two_robots):
    """The limit held for a declared Content-Length only; chunked, 50 MB went through."""
    pairs, _ = tum_two_robots
    with TestClient(create_app(Settings(max_body_bytes=10_000))) as c:
        r = c.post(
            "/align",
            content=(b"x" * 4096 for _ in range(100)),
            headers={"content-type": "multipart/form-data; boundary=zz"},
        )
        assert r.status_code == 413 and "10000-byte limit" in r.json()["detail"]


def test_pixel_budget_refuses_a_request_larger_than_itself(tum_two_robots):
    pairs, _ = tum_two_robots
    with TestClient(create_app(Settings(max_pixels_in_flight=500_000))) as c:
        r = c.post("/align", **_request(pairs))  # two 640x480 views: 1.2 Mpx
        assert r.status_code == 413 and "pixel budget" in r.json()["detail"]
