"""The place database on PostgreSQL: two `fleetmap serve place-db --database URL` replicas
over one real PostgreSQL server, robots ingested through different replicas, one replica
SIGKILLed, the server restarted under them. Replicas merging live: tests/e2e/test_live_map.py."""

import threading
import time

import httpx
import pytest

from fleetmap.client import PlaceDBClient
from fleetmap.place import PlaceDB
from tests import pg
from tests.helpers import OCTET, ingest
from tests.servers import Service


def _replica(url: str, tmp_path, k: int, **env) -> Service:
    env = {"FLEETMAP_PLACE_DB_DATABASE": url, **env}
    return Service("place-db", tmp_path / f"r{k}", env=env).start()


def _wait(predicate, timeout: float = 30.0, poll_s: float = 0.05):
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(poll_s)


def _pairs(overlaps) -> set:
    return {(o["stamp_a"], o["stamp_b"]) for o in overlaps}


def test_replicas_share_keyframes_and_compute_overlaps_once(pg_url, tmp_path, sun3d_frames):
    one, two = _replica(pg_url, tmp_path, 1), _replica(pg_url, tmp_path, 2)
    try:
        with (
            httpx.Client(base_url=one.url, timeout=60) as a,
            httpx.Client(base_url=two.url, timeout=60) as b,
        ):
            for d in sun3d_frames["robot_a"]:  # robot A through replica one
                assert (
                    a.post("/robots/robot_a/keyframes", content=d, headers=OCTET).status_code == 201
                )
            for d in sun3d_frames["robot_b"]:  # robot B through replica two
                assert (
                    b.post("/robots/robot_b/keyframes", content=d, headers=OCTET).status_code == 201
                )
            # a keyframe acknowledged by one is found by queries on the other
            q = b.post("/query", content=sun3d_frames["robot_a"][3], headers=OCTET).json()
            assert q["database_size"] == len(sun3d_frames["robot_a"]) + len(sun3d_frames["robot_b"])
            assert q["winner"] is not None and q["winner"]["robot_id"] == "robot_a"
            params = {"robot_a": "robot_a", "robot_b": "robot_b", "wait": 60}
            on_one = a.get("/overlaps", params=params).json()
            on_two = b.get("/overlaps", params=params).json()
            assert on_one["pending"] == 0 and on_two["pending"] == 0
            assert _pairs(on_one["overlaps"]) == _pairs(on_two["overlaps"]) != set()
            # computed once: each keyframe of the pair appears in at most one cascade row
            kfs = [o["keyframe_a"] for o in on_one["overlaps"] if o["source"] == "cascade"]
            assert len(kfs) == len(set(kfs))
    finally:
        one.stop()
        two.stop()


def test_same_overlaps_on_either_backend(pg_url, tmp_path, sun3d_frames, vocabulary):
    found = {}
    for name, store in (("sqlite", tmp_path / "p.sqlite"), ("postgres", pg_url)):
        db = PlaceDB(store, vocabulary, background=False)
        try:
            for robot in ("robot_a", "robot_b"):
                db.add_keyframes(robot, sun3d_frames[robot])
            db.process_pending()
            found[name] = {
                (o.stamp_a, o.stamp_b, o.inliers) for o in db.overlaps("robot_a", "robot_b")
            }
        finally:
            db.close()
    assert found["sqlite"] == found["postgres"] != set()


def test_sigkill_of_a_replica_loses_no_acknowledged_keyframe(pg_url, tmp_path, fleet_frames):
    one, two = _replica(pg_url, tmp_path, 1), _replica(pg_url, tmp_path, 2)
    acked, errors = [], []
    robots = list(fleet_frames.items())
    threads = [
        threading.Thread(target=ingest, args=(svc.url, r, fs, acked, errors))
        for k, (r, fs) in enumerate(robots[:6])
        for svc in [(one, two)[k % 2]]
    ]
    try:
        for t in threads:
            t.start()
        _wait(lambda: len(acked) >= 40)
        one.kill()  # SIGKILL while its robots are still posting
        for t in threads:
            t.join(60)
        assert not errors
        with httpx.Client(base_url=two.url, timeout=60) as c:
            _wait(lambda: c.get("/overlaps", params={"wait": 5}).json()["pending"] == 0, 120)
            counts = {r["robot_id"]: r["keyframes"] for r in c.get("/robots").json()["robots"]}
            for _, kf_id, data in acked:
                assert c.get(f"/keyframes/{kf_id}/frame").content == data
            for robot in {a[0] for a in acked}:
                assert counts[robot] >= sum(a[0] == robot for a in acked)
            # the killed replica's claims went back to the queue and were done by the other
            assert c.get("/healthz").json()["pending"] == 0
        # clients given both replicas fail over to the live one
        with PlaceDBClient(f"{one.url},{two.url}", timeout=10) as client:
            assert {r["robot_id"] for r in client.robots()} >= {a[0] for a in acked}
    finally:
        one.stop()
        two.stop()


@pytest.mark.skipif(not pg.available(), reason="PostgreSQL binaries not found")
def test_postgres_restart_is_503_then_served_again(tmp_path, sun3d_frames):
    cluster = pg.Cluster().start()
    try:
        url = cluster.database()
        # a pooled connection waited for 1 s, not 5, before the 503: PostgreSQL is down here
        svc = _replica(url, tmp_path, 1, FLEETMAP_PLACE_DB_PG_TIMEOUT_S="1")
        try:
            with httpx.Client(base_url=svc.url, timeout=60) as c:
                d0, d1 = sun3d_frames["robot_a"][:2]
                assert (
                    c.post("/robots/robot_a/keyframes", content=d0, headers=OCTET).status_code
                    == 201
                )
                cluster.stop()
                r = c.post("/robots/robot_a/keyframes", content=d1, headers=OCTET)
                assert r.status_code == 503 and "PostgreSQL" in r.json()["detail"], r.text
                assert "retry-after" in r.headers
                r = c.get("/robots")
                assert r.status_code == 503 and "unreachable" in r.json()["detail"]
                assert c.get("/healthz").status_code == 503
                cluster.start()  # back: served again without restarting the replica
                _wait(lambda: c.get("/robots").status_code == 200)
                # the pool reconnects its other connections in the background: a robot
                # retries a 503 (as the clients do) and is served
                _wait(
                    lambda: (
                        c.post("/robots/robot_a/keyframes", content=d1, headers=OCTET).status_code
                        in (200, 201)
                    ),
                    60,
                )
                robots = c.get("/robots").json()["robots"]
                assert [(r["robot_id"], r["keyframes"]) for r in robots] == [("robot_a", 2)]
        finally:
            svc.stop()
    finally:
        cluster.remove()


def test_a_keyframe_failing_detection_is_parked_and_the_rest_go_on(
    pg_url, sun3d_frames, vocabulary
):
    """A stored frame corrupted: its detection raises; after three attempts it is parked
    (listed, out of the queue) and every other keyframe is processed."""
    import psycopg

    db = PlaceDB(pg_url, vocabulary, background=False)
    try:
        ids = [kf for kf, _ in db.add_keyframes("robot_a", sun3d_frames["robot_a"])]
        ids += [kf for kf, _ in db.add_keyframes("robot_b", sun3d_frames["robot_b"])]
        with psycopg.connect(pg_url, autocommit=True) as con:
            con.execute("UPDATE keyframes SET data = '\\x00'::bytea WHERE id = %s", (ids[3],))
        db.process_pending()
        st = db.stats()
        assert st["pending"] == 0 and st["worker_failures"] == 3
        assert list(st["parked"]) == [ids[3]] and st["storage_errors"] >= 3
        assert db.overlaps("robot_a", "robot_b")  # the others were processed
    finally:
        db.close()
