"""The aligner over HTTP (in-process TestClient)."""

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.aligner.config import Settings
from services.aligner.main import create_app
from shared.client import align_request
from shared.geometry import transform_error
from tests.test_align import tum_two_robots  # noqa: F401  (fixture)


@pytest.fixture
def client():
    with TestClient(create_app(Settings(max_body_bytes=20_000_000))) as c:
        yield c


def _request(pairs, **meta_kw):
    return align_request(pairs, **meta_kw)


def test_align_returns_the_transform_and_a_merged_ply(client, tum_two_robots):  # noqa: F811
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
def test_baseline_methods(client, tum_two_robots, method):  # noqa: F811
    pairs, T_a_b = tum_two_robots
    body = client.post("/align", **_request(pairs, method=method)).json()
    assert body["method"] == method
    if method != "mlp":
        assert transform_error(np.array(body["transform"]), T_a_b)[0] < 0.1


def test_bad_requests_answer_4xx(client, tum_two_robots):  # noqa: F811
    pairs, _ = tum_two_robots
    req = _request(pairs)
    del req["files"]["b0_depth"]
    r = client.post("/align", **req)
    assert r.status_code == 422 and "b0_depth" in r.json()["detail"]

    req = _request(pairs)
    req["files"]["a0_rgb"] = ("x.png", b"not an image")
    r = client.post("/align", **req)
    assert r.status_code == 422 and "does not decode" in r.json()["detail"]

    a, b = pairs[0]
    req = _request(pairs)
    req["files"]["a0_depth"] = ("x.png", cv2.imencode(".png", a.depth[:100])[1].tobytes())
    r = client.post("/align", **req)
    assert r.status_code == 422 and "does not match colour" in r.json()["detail"]

    req = _request(pairs)
    req["files"]["b0_depth"] = ("x.png", cv2.imencode(".png", np.zeros_like(b.depth))[1].tobytes())
    assert "no valid reading" in client.post("/align", **req).json()["detail"]

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


def test_inline_pair_layout_still_accepted(client, tum_two_robots):  # noqa: F811
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
    assert client.get("/clouds/nope").status_code == 404


def test_oversized_body_is_refused(tum_two_robots):  # noqa: F811
    pairs, _ = tum_two_robots
    with TestClient(create_app(Settings(max_body_bytes=1000))) as c:
        r = c.post("/align", **_request(pairs))
        assert r.status_code == 413
