"""Access control, compressed and oversized bodies, and what the logs never show."""

import gzip
import logging

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.frame import decode, encode
from fleetmap.services.aligner.config import Settings as AlignerSettings
from fleetmap.services.aligner.main import create_app as create_aligner
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from tests.helpers import OCTET, make_frame

OP, TOK_A, TOK_B = "op-secret-123", "robot-a-secret", "robot-b-secret"


def _frame(robot: str, stamp: float = 1.0) -> bytes:
    from fleetmap.vocabulary import load_vocabulary

    f = make_frame(robot_id=robot, stamp=stamp)
    f.vocab_id = load_vocabulary().vocab_id
    return encode(f)


@pytest.fixture
def secured(tmp_path):
    st = Settings(data_dir=tmp_path, operator_token=OP, robot_tokens={"A": TOK_A, "B": TOK_B})
    with TestClient(create_app(st)) as c:
        yield c


def _auth(tok):
    return {"authorization": f"Bearer {tok}"}


def test_robot_tokens_write_only_their_own_robot(secured):
    post = secured.post
    assert post("/robots/A/keyframes", content=_frame("A"), headers=OCTET).status_code == 401
    r = post("/robots/A/keyframes", content=_frame("A"), headers={**OCTET, **_auth("nope")})
    assert r.status_code == 401 and r.json()["detail"] == "Invalid token"
    r = post("/robots/A/keyframes", content=_frame("A"), headers={**OCTET, **_auth(TOK_B)})
    assert r.status_code == 403 and "robot 'B' may not write robot 'A'" in r.json()["detail"]
    assert (
        post(
            "/robots/A/keyframes", content=_frame("A"), headers={**OCTET, **_auth(TOK_A)}
        ).status_code
        == 201
    )
    assert (
        post("/robots/B/keyframes", content=_frame("B"), headers={**OCTET, **_auth(OP)}).status_code
        == 201
    )  # operator may write


def test_operator_token_reads_and_administers(secured):
    for method, path in [
        ("get", "/robots"),
        ("get", "/overlaps"),
        ("get", "/stats"),
        ("delete", "/robots/A"),
        ("post", "/admin/retrain"),
        ("get", "/links"),
        ("put", "/links/A/B"),
        ("get", "/map/pose_graph.g2o"),
    ]:
        assert getattr(secured, method)(path, headers=_auth(TOK_A)).status_code == 403, path
        assert getattr(secured, method)(path).status_code == 401, path
    assert secured.get("/robots", headers=_auth(OP)).json() == {"robots": []}
    # robots may query and read the vocabulary; health is open
    assert secured.get("/vocabulary", headers=_auth(TOK_A)).status_code == 200
    assert (
        secured.post("/query", content=_frame("A"), headers={**OCTET, **_auth(TOK_A)}).status_code
        == 200
    )
    assert secured.get("/healthz").status_code == 200


def test_tokens_never_reach_the_logs(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    st = Settings(data_dir=tmp_path, operator_token=OP, robot_tokens={"A": TOK_A})
    with TestClient(create_app(st)) as c:
        c.post("/robots/A/keyframes", content=_frame("A"), headers={**OCTET, **_auth(TOK_A)})
        c.get("/robots", headers=_auth("wrong-token-xyz"))
    text = caplog.text + repr(st)
    assert "access control on" in caplog.text
    for secret in (OP, TOK_A, "wrong-token-xyz"):
        assert secret not in text


def test_open_deployment_says_so(tmp_path, caplog):
    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        assert c.get("/robots").status_code == 200
    assert "access control OFF" in caplog.text


def test_an_open_service_is_an_alarm_beyond_loopback_only():
    """Issue 25: services `merge` starts itself on loopback printed 'anyone on the network
    may read and write'."""
    from fleetmap.services.common import auth_summary

    open_ = Settings()
    for host in ("127.0.0.1", "localhost", "::1"):
        assert "anyone on the network" not in auth_summary(open_, host)
    for host in ("0.0.0.0", "192.168.1.20", "::", None):
        assert "access control OFF" in auth_summary(open_, host)
    secured = Settings(operator_token=OP)
    assert auth_summary(secured, "0.0.0.0").startswith("access control on")


def test_compressed_bodies_are_refused_and_nothing_is_stored(tmp_path):
    with TestClient(create_app(Settings(data_dir=tmp_path, max_body_bytes=100_000))) as c:
        bomb = gzip.compress(bytes(50_000_000))  # 50 MB of zeros in ~50 KB
        r = c.post(
            "/robots/A/keyframes", content=bomb, headers={**OCTET, "content-encoding": "gzip"}
        )
        assert r.status_code == 415 and "gzip" in r.json()["detail"]
        r = c.post("/robots/A/keyframes", content=bytes(200_000), headers=OCTET)
        assert r.status_code == 413
        assert c.get("/robots").json() == {"robots": []}


def test_aligner_requires_a_token_when_configured():
    st = AlignerSettings(operator_token=OP)
    with TestClient(create_aligner(st)) as c:
        assert c.post("/align", data={"meta": "{}"}).status_code == 401
        r = c.post("/align", data={"meta": "{}"}, headers=_auth(OP))
        assert r.status_code == 422  # authorised, then the bad request is named
        assert c.get("/healthz").status_code == 200


def test_frame_robot_must_match_even_with_operator_token(secured):
    f = decode(_frame("A"))
    r = secured.post("/robots/B/keyframes", content=encode(f), headers={**OCTET, **_auth(OP)})
    assert r.status_code == 422 and "posted for 'B'" in r.json()["detail"]


@pytest.mark.parametrize("kind", ["place-db", "aligner"])
def test_openapi_declares_bearer_errors_and_serves_its_docs_offline(tmp_path, kind):
    """Issue 14: no security scheme (no Authorize button), only 422 declared, /align with
    no body in the schema, /docs loading Swagger UI from a CDN (blank on an offline robot
    network)."""
    import re

    app = create_app(Settings(data_dir=tmp_path)) if kind == "place-db" else create_aligner()
    with TestClient(app) as c:
        spec = c.get("/openapi.json").json()
        assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
        path, method = ("/overlaps", "get") if kind == "place-db" else ("/align", "post")
        op = spec["paths"][path][method]
        assert op["security"] == [{"HTTPBearer": []}]
        assert {"401", "403", "413", "503"} <= set(op["responses"])
        if kind == "aligner":
            assert "multipart/form-data" in op["requestBody"]["content"]
        page = c.get("/docs").text
        assert not re.findall(r"https?://(?!127\.0\.0\.1)", page)  # nothing fetched from outside
        for asset in re.findall(r"(/static/swagger/[\w.-]+)", page):
            assert c.get(asset).status_code == 200


def test_the_live_pose_graph_is_served_only_for_the_current_placement(secured):
    """`GET /map/pose_graph.g2o`: 404 naming the placement before a graph is solved and
    after the placement moved on; the stored g2o text as it was solved in between."""
    from fleetmap.fleet.state import write_graph, write_placement
    from fleetmap.fleet.types import Placement

    db = secured.app.state.db
    r = secured.get("/map/pose_graph.g2o", headers=_auth(OP))
    assert r.status_code == 404 and r.json()["error"] == "NotSolved", r.text
    assert "placement 0" in r.json()["detail"]
    text = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
    write_placement(db, Placement("A", {"A": np.eye(4)}, version=3))
    write_graph(db, {"version": 3, "summary": {}, "robots": {}}, text)
    r = secured.get("/map/pose_graph.g2o", headers=_auth(OP))
    assert r.status_code == 200 and r.text == text
    assert r.headers["content-type"].startswith("text/plain")
    write_placement(db, Placement("A", {"A": np.eye(4)}, version=4))  # a newer placement
    r = secured.get("/map/pose_graph.g2o", headers=_auth(OP))
    assert r.status_code == 404 and "placement 4" in r.json()["detail"]
