"""The place database as a real process, driven over HTTP by the CLI and httpx."""

import json
from pathlib import Path

from fleetmap.services.cli import main
from tests.servers import Service, http


def test_cli_ingest_overlaps_and_sigkill_restart(sun3d, tmp_path, capsys):
    svc = Service("place-db", tmp_path / "db").start()
    try:
        assert (
            main(
                [
                    "ingest",
                    f"A={sun3d / 'robot_a'}",
                    f"B={sun3d / 'robot_b'}",
                    "--place-db",
                    svc.url,
                ]
            )
            == 0
        )
        capsys.readouterr()
        assert main(["overlaps", "B", "A", "--place-db", svc.url, "--json"]) == 0
        first = json.loads(capsys.readouterr().out)["overlaps"]
        assert first and all(o["robot_a"] == "B" and o["inliers"] >= 10 for o in first)
        robots = http.get(svc.url + "/robots").json()["robots"]
    finally:
        svc.kill()
    again = Service("place-db", tmp_path / "db")
    again.port, again.url = svc.port, svc.url
    again.start()
    try:
        assert http.get(svc.url + "/robots").json()["robots"] == robots
        assert main(["overlaps", "B", "A", "--place-db", svc.url, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["overlaps"] == first
    finally:
        again.stop()


def test_cli_reports_unreachable_service_and_unknown_robot(tmp_path, capsys):
    assert main(["overlaps", "A", "B", "--place-db", "http://127.0.0.1:9"]) == 1
    assert "Cannot reach" in capsys.readouterr().err
    svc = Service("place-db", tmp_path / "db").start()
    try:
        assert main(["overlaps", "A", "B", "--place-db", svc.url]) == 1
        assert "Unknown robot 'A'" in capsys.readouterr().err
        example = Path(__file__).parents[2] / "examples" / "fr1_pair"
        pair = [str(example / r) for r in ("alpha", "bravo")]
        argv = ["align", *pair, "--place-db", svc.url, "--aligner", "http://127.0.0.1:9"]
        assert main(argv) == 1  # before `ingest`: said how to go on
        hint = "Unknown robot 'alpha' (`fleetmap ingest` its folder first)"
        assert hint in capsys.readouterr().err
    finally:
        svc.stop()
