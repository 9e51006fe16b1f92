"""The live fleet map (CONTRACT section 6): robots streamed by `fleetmap stream` into real
`fleetmap serve place-db --aligner URL` processes, merged by their worker as overlaps appear:
two replicas over one PostgreSQL database (one leads the merging at a time) serving the same
`GET /map`, against the simulated fleet's true transforms; `fleetmap map`; the operator page;
a restart mid-stream (SQLite)."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from fleetmap.geometry import transform_error
from fleetmap.services.cli import main
from tests.browser import chromium_dom, chromium_screenshot
from tests.conftest import write_robot
from tests.servers import LIVE_FAST, Service, http

pytestmark = pytest.mark.slow


def wall_robot(folder):
    """A robot that saw only a blank wall: it shares no place with anyone."""
    folder.mkdir(parents=True, exist_ok=True)
    img, depth = folder / "wall.png", folder / "wall_depth.png"
    cv2.imwrite(str(img), np.full((480, 640, 3), 128, np.uint8))
    cv2.imwrite(str(depth), np.full((480, 640), 5000, np.uint16))
    return write_robot(folder / "wall", [(300.0, img, depth, np.eye(4))])


def wait_map(
    url: str, placed: int, merged_pairs: int = 0, timeout: float = 240.0, headers=None
) -> dict:
    """The map once `placed` robots are placed and `merged_pairs` pairs merged."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        m = http.get(url + "/map", headers=headers, timeout=30).json()
        merged = sum(p["status"] == "merged" for p in m["pairs"])
        if len(m["transforms"]) >= placed and merged >= merged_pairs:
            return m
        time.sleep(0.5)
    raise AssertionError(f"{placed} robots not placed within {timeout} s: {m}")


def settled(url: str, quiet_s: float = 2.5, timeout: float = 120.0) -> dict:
    """The map once no pair has been aligned for `quiet_s` seconds."""
    end, last, since = time.monotonic() + timeout, None, time.monotonic()
    while time.monotonic() < end:
        m = http.get(url + "/map", headers=AUTH, timeout=30).json()
        key = [p["attempts"] for p in m["pairs"]]
        w = m["worker"]
        busy = w is None or w["aligning"] or w["due"] or not w.get("quiet")
        if key != last or busy:
            last, since = key, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return m
        time.sleep(0.5)
    raise AssertionError(f"the merge worker kept aligning for {timeout} s")


def check_truth(m: dict, truth: dict) -> None:
    ref = m["reference"]
    for robot, T in m["transforms"].items():
        # T_true maps each robot's frame into robot0's: into the reference's through it
        T_true = np.linalg.inv(np.array(truth[ref])) @ np.array(truth[robot])
        dt, dr = transform_error(np.array(T), T_true)
        assert dt < 0.05 and dr < 2.0, (robot, dt, dr)


TOKEN = "operator-secret-7"
AUTH = {"authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def live(sim_fleet, aligner_url, pg_cluster, tmp_path_factory):
    """Two token-protected place-db replicas with a merge worker each over one PostgreSQL
    database, the fleet and a wall robot streamed through both (comma-separated URLs), once
    every pair is merged: (replica one, replica two, the map)."""
    sim, truth = sim_fleet
    tmp = tmp_path_factory.mktemp("live")
    env = {"FLEETMAP_PLACE_DB_OPERATOR_TOKEN": TOKEN, "FLEETMAP_TOKEN": TOKEN, **LIVE_FAST}
    env |= {"FLEETMAP_PLACE_DB_DATABASE": pg_cluster.database()}
    args = ["--aligner", aligner_url]
    one = Service("place-db", tmp / "r1", env=env, args=args).start()
    two = Service("place-db", tmp / "r2", env=env, args=args).start()
    try:
        robots = [str(sim / r) for r in truth] + [str(wall_robot(tmp / "w"))]
        urls = f"{one.url},{two.url}"
        args = ["--token", TOKEN, "stream", *robots, "--place-db", urls, "--speed", "0"]
        assert main(args) == 0
        m = wait_map(one.url, 3, merged_pairs=3, headers=AUTH)  # every pair overlaps: a cycle
        yield one, two, m
    finally:
        one.stop()
        two.stop()


def test_streamed_fleet_is_merged_live_and_written_by_map(live, sim_fleet, tmp_path, capsys):
    db, _, m = live
    _, truth = sim_fleet
    assert m["reference"] == "robot0" and m["robots"] == ["robot0", "robot1", "robot2", "wall"]
    check_truth(m, truth)
    assert m["unmerged"] == [
        {"robot": "wall", "reason": "no verified overlap with another robot yet"}
    ]
    m = settled(db.url)  # refinements as overlaps doubled, then nothing new:
    time.sleep(2)  # no pair aligned again, the version unchanged
    again = http.get(db.url + "/map", headers=AUTH).json()
    assert again["version"] == m["version"]
    assert [p["attempts"] for p in again["pairs"]] == [p["attempts"] for p in m["pairs"]]
    check_truth(again, truth)
    assert http.get(db.url + "/map").status_code == 401  # token-protected
    kfs = http.get(db.url + "/robots/robot1/keyframes", headers=AUTH).json()["keyframes"]
    assert len(kfs) == 12
    view = http.get(db.url + f"/keyframes/{kfs[0]['id']}/view", headers=AUTH).json()
    assert view["robot_id"] == "robot1" and view["rgb_type"] == "image/jpeg"
    depth = http.get(db.url + f"/keyframes/{kfs[0]['id']}/view/depth", headers=AUTH).content
    assert cv2.imdecode(np.frombuffer(depth, np.uint8), cv2.IMREAD_UNCHANGED).dtype == np.uint16

    out = tmp_path / "map"
    assert main(["--token", TOKEN, "map", "--place-db", db.url, "-o", str(out)]) == 0
    assert "unmerged wall: no verified overlap" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["transforms"] == again["transforms"] and report["unmerged"] == ["wall"]
    assert (out / "overview.png").stat().st_size > 10_000
    assert (out / "overlap_matrix.png").stat().st_size > 5_000
    ply = (out / "merged.ply").read_bytes()
    assert b"property uint16 robot" in ply[:400]
    assert int(ply.split(b"element vertex ")[1].split()[0]) > 1000
    g2o = (out / "pose_graph.g2o").read_text()
    n = g2o.count("VERTEX_SE3:QUAT")
    if n == 3:  # no keyframe graph solved yet on this placement: the robots' graph
        assert g2o.count("EDGE_SE3:QUAT") == 3
    else:  # the idle worker solved the keyframe graph: a vertex per keyframe, odometry,
        # and at least two closures tying the three robots (run alone, it is solved by now)
        assert n == 3 * 12 and g2o.count("EDGE_SE3:QUAT") >= 3 * 11 + 2, g2o[:300]
    assert len((out / "trajectories" / "robot2.txt").read_text().splitlines()) == 1 + 12
    from mcap.reader import make_reader  # fleet.mcap, as merge writes it (issue 25)

    with (out / "fleet.mcap").open("rb") as f:
        topics = {c.topic: s.name for s, c, _ in make_reader(f).iter_messages()}
    assert (
        topics["/fleet/robot2/cloud"] == "foxglove.PointCloud" and "/fleet/wall/cloud" not in topics
    )
    assert topics["/tf"] == "foxglove.FrameTransform"


def test_both_replicas_serve_one_map_each_pair_aligned_once(live, sim_fleet):
    """Over PostgreSQL every pair is aligned by one replica only (the advisory lock), and
    both serve the same map, within 5 cm / 2 deg of the truth."""
    one, two, _ = live
    m = settled(two.url)  # a GET /map (the map built from PostgreSQL) every 0.5 s
    assert http.get(one.url + "/map", headers=AUTH).json()["transforms"] == m["transforms"]
    assert m["reference"] == "robot0" and [u["robot"] for u in m["unmerged"]] == ["wall"]
    check_truth(m, sim_fleet[1])
    started = sum(s.read_log().count("live map: aligning") for s in (one, two))
    assert started == sum(p["attempts"] for p in m["pairs"])  # no pair aligned twice


def test_3d_view_draws_every_placed_robot_offline(live):
    """Issue 25: the page's 3D view, three.js served by the place database itself."""
    from fleetmap.mapcloud import ROBOT_COLOURS

    db, _, _ = live
    r = http.get(db.url + "/map/robots/robot1/cloud.bin", headers=AUTH)
    n = int(r.headers["x-points"])
    assert r.status_code == 200 and len(r.content) == 15 * n and 1000 < n and len(r.content) <= 2e6
    xyz = np.frombuffer(r.content, "<f4", 3 * n).reshape(n, 3)
    assert np.isfinite(xyz).all()
    assert http.get(db.url + "/map/robots/robot1/cloud.bin").status_code == 401
    assert http.get(db.url + "/map/robots/nobody/cloud.bin", headers=AUTH).status_code == 404
    lines = http.get(db.url + "/map/lines", headers=AUTH).json()
    assert lines["overlaps"] and {ln[0] for ln in lines["overlaps"]} <= {"robot0", "robot1"}
    page = http.get(db.url + "/").text
    assert "/static/map3d/map3d.bundle.js" in page and "://" not in page  # no CDN
    bundle = http.get(db.url + "/static/map3d/map3d.bundle.js")  # code, no data: no token
    assert bundle.status_code == 200 and b"Three.js Authors" in bundle.content
    img = chromium_screenshot(f"{db.url}/#token={TOKEN}&view=3d").astype(int)
    # each placed robot's points in its own colour (drawn unlit, colours as given)
    for k, robot in enumerate(["robot0", "robot1", "robot2", "wall"]):
        bgr = np.round(ROBOT_COLOURS[k][::-1] * 255)
        near = (np.abs(img - bgr).max(axis=2) <= 6).sum()
        assert (near > 300) if robot != "wall" else (near == 0), (robot, near)


def test_operator_page_in_a_real_browser(live):
    db, _, _ = live
    m = http.get(db.url + "/map", headers=AUTH).json()
    dom = chromium_dom(f"{db.url}/#token={TOKEN}")
    assert f'data-version="{m["version"]}"' in dom  # the script ran and read the map
    assert f"map version {m['version']}: 3 of 4 robots placed, reference robot0" in dom
    for r in ("robot1", "robot2"):
        row = '<td class="n">12</td><td class="n">12</td><td class="merged">merged</td>'
        assert f'<tr data-robot="{r}"><td>{r}</td>{row}</tr>' in dom
    assert '<li data-robot="wall">wall: no verified overlap with another robot yet</li>' in dom
    assert 'id="overview" alt="overview of the live map (top-down)" src="blob:' in dom
    assert 'id="error"></div>' in dom  # no error shown
    # without the token: the login form, no robot data
    dom = chromium_dom(db.url + "/")
    assert "token refused" in dom and 'id="login" style="display: block;"' in dom
    assert "robot1" not in dom


def test_restart_mid_stream_loses_nothing_and_resumes_the_map(
    sim_fleet, aligner_url, tmp_path, capsys
):
    sim, truth = sim_fleet
    data = tmp_path / "db"
    db = Service("place-db", data, env=LIVE_FAST, args=["--aligner", aligner_url]).start()
    try:
        assert (
            main(
                [
                    "stream",
                    str(sim / "robot0"),
                    str(sim / "robot1"),
                    "--place-db",
                    db.url,
                    "--speed",
                    "0",
                ]
            )
            == 0
        )
        wait_map(db.url, 2)
        before = settled(db.url)  # aligned on every overlap found
        db.kill()  # no chance to flush anything
        db = Service("place-db", data, env=LIVE_FAST, args=["--aligner", aligner_url]).start()
        m = http.get(db.url + "/map").json()
        assert m["version"] == before["version"] and m["transforms"] == before["transforms"]
        # the rest of the stream (the robots' earlier keyframes again: idempotent)
        robots = [str(sim / r) for r in truth]
        assert main(["stream", *robots, "--place-db", db.url, "--speed", "0"]) == 0
        m = wait_map(db.url, 3)
        check_truth(m, truth)
        pair01 = next(p for p in m["pairs"] if (p["robot_a"], p["robot_b"]) == ("robot0", "robot1"))
        first01 = next(
            p for p in before["pairs"] if (p["robot_a"], p["robot_b"]) == ("robot0", "robot1")
        )
        assert pair01["attempts"] == first01["attempts"]  # no new evidence: not aligned again
        robots_after = {
            r["robot_id"]: r["keyframes"] for r in http.get(db.url + "/robots").json()["robots"]
        }
        assert robots_after == {"robot0": 12, "robot1": 12, "robot2": 12}
    finally:
        db.stop()
    capsys.readouterr()
