"""Issue 15's attacks, each answered cleanly: every one of these was a 500, a silent
acceptance or a leak before (the test names say which)."""

from __future__ import annotations

import sqlite3
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.frame import decode
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from tests.helpers import OCTET, post_frame


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        yield c


def _with_pose(data: bytes, T: np.ndarray) -> bytes:
    f = decode(data)
    f.T_map_cam = T  # bypasses validation: what a hostile client could encode by hand
    header_start = 12
    magic, version, flags, hlen = struct.unpack_from("<4sHHI", data)
    import json

    h = json.loads(data[header_start : header_start + hlen])
    h["T_map_cam"] = T.tolist()
    header = json.dumps(h, separators=(",", ":")).encode()
    body = struct.pack("<4sHHI", magic, version, flags, len(header)) + header
    body += data[header_start + hlen : -4]
    return body + struct.pack("<I", zlib.crc32(body))


def test_an_all_zero_pose_is_refused_at_ingest(client, sun3d_frames):
    """Was 201, then every link for the pair answered 500 (singular matrix)."""
    r = post_frame(client, "robot_a", _with_pose(sun3d_frames["robot_a"][0], np.zeros((4, 4))))
    assert r.status_code == 400 and "bottom row" in r.json()["detail"]
    scaled = _with_pose(sun3d_frames["robot_a"][0], np.diag([3.0, 3.0, 3.0, 1.0]))
    r = post_frame(client, "robot_a", scaled)
    assert r.status_code == 400 and "rigid" in r.json()["detail"]
    assert client.get("/robots").json()["robots"] == []  # nothing stored


def test_out_of_range_query_parameters_are_4xx(client, sun3d_frames):
    """?offset >= 2^63 was a 500; ?max_stamp=nan was accepted."""
    post_frame(client, "robot_a", sun3d_frames["robot_a"][0])
    r = client.get("/robots/robot_a/keyframes", params={"offset": 2**63})
    assert r.status_code == 422
    r = client.post(
        "/query", content=sun3d_frames["robot_a"][0], headers=OCTET, params={"max_stamp": "nan"}
    )
    assert r.status_code == 422


def test_a_corrupted_stored_frame_is_a_storage_error_not_the_clients(tmp_path, sun3d_frames):
    """16 bytes corrupted in storage: GET returned the wrong bytes with 200 and a valid
    query got a 400 blaming the client. Now: 500 naming the keyframe, counted in /healthz,
    and queries still answered from the other keyframes."""
    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        ids = [post_frame(c, "robot_a", d).json()["id"] for d in sun3d_frames["robot_a"]]
    db_file = next(tmp_path.glob("*.sqlite*"))
    con = sqlite3.connect(db_file)
    data = bytearray(con.execute("SELECT data FROM keyframes WHERE id=?", (ids[0],)).fetchone()[0])
    data[100:116] = bytes(16)
    con.execute("UPDATE keyframes SET data=? WHERE id=?", (bytes(data), ids[0]))
    con.commit()
    con.close()
    with TestClient(create_app(Settings(data_dir=tmp_path))) as c:
        r = c.get(f"/keyframes/{ids[0]}/frame")
        assert r.status_code == 500 and f"Keyframe {ids[0]}" in r.json()["detail"]
        assert r.json()["error"] == "StorageCorrupt"
        h = c.get("/healthz").json()
        assert h["storage_errors"] == 1 and h["status"] == "degraded"
        q = c.post("/query", content=sun3d_frames["robot_a"][1], headers=OCTET)
        assert q.status_code == 200
        assert c.get(f"/keyframes/{ids[1]}/frame").content == sun3d_frames["robot_a"][1]


def test_secured_healthz_tells_anonymous_callers_liveness_only(tmp_path):
    """With tokens on, /healthz showed anyone the database path and counts."""
    settings = Settings(data_dir=tmp_path, operator_token="op-secret")
    with TestClient(create_app(settings)) as c:
        anon = c.get("/healthz").json()
        assert anon == {"status": "ok"}
        full = c.get("/healthz", headers={"authorization": "Bearer op-secret"}).json()
        assert full["database"].startswith(str(tmp_path)) and full["keyframes"] == 0


def test_request_ids_are_sanitised(client):
    """An X-Request-Id with a newline was logged as is (log injection)."""
    r = client.get("/healthz", headers={"x-request-id": "abc\r\nfake log line"})
    assert "\n" not in r.headers["x-request-id"] and r.headers["x-request-id"] != "abc"
    r = client.get("/healthz", headers={"x-request-id": "robot-7.req:42"})
    assert r.headers["x-request-id"] == "robot-7.req:42"


def test_a_token_in_the_query_string_never_reaches_the_log(tmp_path):
    """uvicorn's access line logged `?token=...` verbatim; now only our request line, path
    without the query string."""

    from tests.servers import Service, http

    svc = Service("place-db", tmp_path / "db").start()
    try:
        assert http.get(svc.url + "/healthz", params={"token": "SUPERSECRET123"}).status_code == 200
    finally:
        svc.stop()
    log = svc.read_log()
    assert "/healthz" in log and "SUPERSECRET123" not in log


def test_a_keyframe_failing_in_the_worker_is_parked_and_blocks_no_other(
    tmp_path,
    sun3d_frames,
    vocabulary,
):
    """A keyframe whose overlap detection raises (here: its stored frame corrupted) is
    counted and parked with its reason; the others are processed and overlap as before."""
    from fleetmap.place import PlaceDB

    db = PlaceDB(tmp_path / "p.sqlite", vocabulary, background=False)
    ids = [db.add_keyframe("robot_a", d)[0] for d in sun3d_frames["robot_a"]]
    ids += [db.add_keyframe("robot_b", d)[0] for d in sun3d_frames["robot_b"]]
    with db.store._write_lock:
        db.store._db.execute("UPDATE keyframes SET data=zeroblob(64) WHERE id=?", (ids[3],))
    db.process_pending()
    st = db.stats()
    assert st["worker_failures"] == 1 and "StorageCorrupt" in st["parked"][ids[3]]
    assert st["pending"] == 0
    assert db.overlaps("robot_a", "robot_b")  # the SUN3D pair's verified overlap still found
    db.close()


def test_a_damaged_database_file_is_one_line_not_a_traceback(tmp_path):
    (tmp_path / "place_db.sqlite").write_bytes(b"this is not sqlite " * 100)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "fleetmap.services.cli",
            "serve",
            "place-db",
            "--data-dir",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1 and "is damaged or not a place database" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_second_place_database_on_one_folder_is_refused_and_the_first_keeps_serving(
    tmp_path, sun3d_frames
):
    """A second `serve place-db` on the same --data-dir started silently; each kept its own
    robot table, so the first answered 404 for robots stored through the second, and its
    live-map worker failed on them in a loop (an outside tester's review, session 51)."""
    from tests.servers import Service, http

    svc = Service("place-db", tmp_path / "db").start()
    try:
        r = http.post(
            svc.url + "/robots/robot_a/keyframes", content=sun3d_frames["robot_a"][0], headers=OCTET
        )
        assert r.status_code == 201
        second = subprocess.run(
            [sys.executable, "-m", "fleetmap.services.cli", "serve", "place-db", "--port", "9",
             "--data-dir", str(tmp_path / "db")],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert second.returncode == 1 and "in use by another process" in second.stderr
        assert "Traceback" not in second.stderr
        assert http.get(svc.url + "/robots/robot_a/keyframes").status_code == 200
    finally:
        svc.stop()
    again = Service("place-db", tmp_path / "db").start()  # stopped: the folder is free again
    try:
        assert http.get(again.url + "/robots/robot_a/keyframes").status_code == 200
    finally:
        again.stop()


@pytest.mark.parametrize("damage", ["delete", "truncate"])
def test_a_lost_write_ahead_log_after_a_crash_is_reported(tmp_path, sun3d_frames, damage):
    """A truncated or deleted WAL silently lost acknowledged keyframes, with no log line."""

    from tests.servers import Service, http

    svc = Service("place-db", tmp_path / "db").start()
    for d in sun3d_frames["robot_a"][:6]:
        r = http.post(svc.url + "/robots/robot_a/keyframes", content=d, headers=OCTET)
        assert r.status_code == 201
    svc.kill()  # SIGKILL: the acknowledged keyframes live in the write-ahead log
    wal = next((tmp_path / "db").glob("*-wal"))
    if damage == "delete":
        wal.unlink()
    else:
        with open(wal, "r+b") as f:
            f.truncate(wal.stat().st_size // 2)
    again = Service("place-db", tmp_path / "db").start()
    try:
        h = http.get(again.url + "/healthz").json()
        assert h["status"] == "degraded" and "were acknowledged" in h["startup_warning"]
    finally:
        again.stop()
    assert "keyframes were lost" in again.read_log()


def test_queries_and_links_racing_deletes_never_answer_5xx(tmp_path, sun3d_frames):
    """/query racing DELETE /robots was a 500 (KeyError), PUT /links racing it an
    IntegrityError 500. Bounded: 4 rounds of delete and re-ingest under queries and links."""
    import threading

    import httpx

    from tests.servers import Service

    svc = Service("place-db", tmp_path / "db").start()
    statuses, stop = [], threading.Event()
    eye = {"transform": np.eye(4).tolist()}

    def hammer() -> None:
        with httpx.Client(base_url=svc.url, timeout=60) as c:
            while not stop.is_set():
                statuses.append(
                    c.post("/query", content=sun3d_frames["robot_b"][0], headers=OCTET).status_code
                )
                statuses.append(c.put("/links/robot_a/robot_b", json=eye).status_code)

    try:
        with httpx.Client(base_url=svc.url, timeout=60) as c:
            for d in sun3d_frames["robot_a"]:
                c.post("/robots/robot_a/keyframes", content=d, headers=OCTET)
            workers = [threading.Thread(target=hammer) for _ in range(2)]
            for w in workers:
                w.start()
            for _ in range(4):
                for d in sun3d_frames["robot_b"]:
                    c.post("/robots/robot_b/keyframes", content=d, headers=OCTET)
                assert c.delete("/robots/robot_b").status_code == 200
            stop.set()
            for w in workers:
                w.join()
        assert statuses and max(statuses) < 500, sorted(set(statuses))
    finally:
        stop.set()
        svc.stop()


def test_slowloris_connections_are_closed(tmp_path):
    """50 connections sending their headers slowly were never closed; now each is cut off
    at the header deadline (10 s; 2 s here, FLEETMAP_PLACE_DB_HEADER_TIMEOUT_S) while the
    service keeps answering."""
    import socket
    import time

    from tests.servers import Service, http

    env = {"FLEETMAP_PLACE_DB_HEADER_TIMEOUT_S": "2"}
    svc = Service("place-db", tmp_path / "db", env=env).start()
    socks = []
    try:
        for _ in range(20):
            s = socket.create_connection(("127.0.0.1", svc.port))
            s.sendall(b"POST /query HTTP/1.1\r\nHost: x\r\n")  # and never the rest
            socks.append(s)
        assert http.get(svc.url + "/healthz").status_code == 200
        end, closed = time.monotonic() + 30, set()
        while time.monotonic() < end and len(closed) < len(socks):
            for k, s in enumerate(socks):
                s.settimeout(0.05)
                try:
                    if s.recv(64) == b"":
                        closed.add(k)
                except TimeoutError:
                    pass
                except OSError:
                    closed.add(k)
        assert len(closed) == len(socks)
    finally:
        for s in socks:
            s.close()
        svc.stop()


def test_frames_sent_as_anything_but_octet_stream_are_415(client, sun3d_frames):
    """Any Content-Type was accepted."""
    r = client.post(
        "/robots/robot_a/keyframes",
        content=sun3d_frames["robot_a"][0],
        headers={"content-type": "text/plain"},
    )
    assert r.status_code == 415 and "application/octet-stream" in r.json()["detail"]
    assert post_frame(client, "robot_a", sun3d_frames["robot_a"][0]).status_code == 201


def test_json_logs_carry_request_fields_and_a_start_line(tmp_path):
    """JSON logs put request id, method, path, status and time in one message string, and
    a served place database printed no 'listening on' line."""
    import json as jsonlib

    from tests.servers import Service, http

    svc = Service("place-db", tmp_path / "db", env={"FLEETMAP_LOG_FORMAT": "json"}).start()
    try:
        http.get(svc.url + "/healthz", headers={"x-request-id": "probe-1"})
    finally:
        svc.stop()
    lines = [jsonlib.loads(x) for x in svc.read_log().splitlines() if x.startswith("{")]
    start = [x for x in lines if "listening on" in x["message"]]
    assert (
        start and f":{svc.port}" in start[0]["message"] and "access control" in start[0]["message"]
    )
    req = [x for x in lines if x.get("request_id") == "probe-1"]
    assert req and req[0]["method"] == "GET" and req[0]["path"] == "/healthz"
    assert req[0]["status"] == 200 and req[0]["ms"] >= 0


def test_healthz_tells_the_access_as_the_start_line_does(tmp_path):
    """An open service on loopback started with "this machine only" and then told every
    /healthz caller "anyone on the network may read and write" (an outside tester's review)."""
    from tests.servers import Service, http

    svc = Service("place-db", tmp_path / "db").start()
    try:
        h = http.get(svc.url + "/healthz").json()
        assert "this machine only" in h["access_control"], h
    finally:
        svc.stop()
