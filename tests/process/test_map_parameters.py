"""`fleetmap map` records the place database's parameters in force (its `GET /config`) in
report.json, from a real service process configured through its environment."""

from __future__ import annotations

import json
from pathlib import Path

from fleetmap.client import PlaceDBClient, services_config
from fleetmap.services.cli import main
from tests.servers import Service

OP, TOK_A = "op-secret-5511", "robot-a-secret-5512"
ALPHA = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair" / "alpha"


def test_map_records_the_place_databases_parameters(tmp_path, capsys):
    env = {
        "FLEETMAP_PLACE_DB_OPERATOR_TOKEN": OP,
        "FLEETMAP_PLACE_DB_ROBOT_TOKENS": json.dumps({"A": TOK_A}),
        "FLEETMAP_PLACE_DB_CASCADE__MAX_VERIFY": "7",
        "FLEETMAP_PLACE_DB_LIVE__SETTLE_S": "3",
    }
    db = Service("place-db", tmp_path / "db", env=env).start()
    try:
        out = tmp_path / "out"
        assert main(["--token", OP, "-q", "ingest", str(ALPHA), "--place-db", db.url]) == 0
        assert main(["--token", OP, "-q", "map", "--place-db", db.url, "-o", str(out)]) == 0
        with PlaceDBClient(db.url, token=OP) as c:
            served = c.config()
        with PlaceDBClient(db.url, token=TOK_A) as c:  # a robot's token may not read it
            refused = services_config(place_db=c)["place_db"]
    finally:
        db.stop()
    capsys.readouterr()
    text = (out / "report.json").read_text()
    params = json.loads(text)["parameters"]
    assert params["voxel_m"] > 0  # the command's own, kept
    report = json.loads(text)  # a map nothing is placed in yet (no aligner): written all the same
    assert report["reference"] is None and report["unmerged"] == ["alpha"]
    g2o = (out / "pose_graph.g2o").read_text()  # "FIX 0" of no vertex 0 before
    assert "VERTEX" not in g2o and "FIX" not in g2o
    assert params["place_db"] == served
    assert served["cascade"]["max_verify"] == 7 and served["live"]["settle_s"] == 3
    assert served["data_dir"] == str(tmp_path / "db")
    assert OP not in text and TOK_A not in text
    assert list(refused) == ["unavailable"] and "operator token" in refused["unavailable"]


def test_map_of_a_database_with_no_robot_is_written_whole(tmp_path, capsys):
    """An IndexError in the pose graph's writer, and a folder left half written, before (an
    outside tester's review, session 51)."""
    db = Service("place-db", tmp_path / "db").start()
    try:
        out = tmp_path / "out"
        assert main(["-q", "map", "--place-db", db.url, "-o", str(out)]) == 0
    finally:
        db.stop()
    assert "0 of 0 robots placed (none yet)" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["robots"] == {} and report["reference"] is None
    assert (out / "fleet.mcap").stat().st_size > 0 and (out / "pose_graph.g2o").is_file()
