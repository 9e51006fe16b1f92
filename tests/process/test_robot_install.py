"""A robot-side install (no `server` extra) posting keyframes to a real place database
process: the place database finds the overlap between two robots ingested that way."""

import json

from tests.robot_side import run_cli
from tests.servers import ROOT, Service

PAIR = ROOT / "examples" / "fr1_pair"


def test_robot_side_ingest_and_overlaps_against_a_real_place_db(tmp_path):
    svc = Service("place-db", tmp_path / "db").start()
    try:
        robots = [f"alpha={PAIR / 'alpha'}", f"bravo={PAIR / 'bravo'}"]
        r = run_cli("-q", "ingest", *robots, "--place-db", svc.url)
        assert r.returncode == 0, r.stderr
        assert r.stdout.splitlines() == [
            "alpha: 1 keyframes ingested",
            "bravo: 1 keyframes ingested",
        ]
        r = run_cli("overlaps", "alpha", "bravo", "--place-db", svc.url, "--json")
        assert r.returncode == 0, r.stderr
        overlaps = json.loads(r.stdout)["overlaps"]
        assert len(overlaps) == 1 and overlaps[0]["inliers"] >= 10
    finally:
        svc.stop()
