"""The command line as a new user meets it: conventions, one-line errors, exit codes, and
the token reaching secured services from every command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from fleetmap.services.cli import main
from tests.servers import ROOT, Service, http

EXAMPLE = ROOT / "examples" / "fr1_pair"


def _run(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    import os

    return subprocess.run(
        [sys.executable, "-m", "fleetmap.services.cli", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        timeout=300,
    )


def test_version_and_help():
    r = _run("--version")
    assert r.returncode == 0 and r.stdout.startswith("fleetmap ")
    r = _run("--help")
    assert "examples:" in r.stdout and "FLEETMAP_PLACE_DB_URL" in r.stdout


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["merge", "nowhere", "-o", "x"], 1, "Robot folder not found"),
        (["merge", "/etc/hostname", "-o", "x"], 1, "is a file, not a robot folder"),
        (["serve", "place-db", "--data-dir", "/proc/x/y"], 1, "/proc/x"),  # cannot be made
        (["merge", str(EXAMPLE / "alpha"), "-o", "/etc/hostname"], 1, "is not a folder"),
        (["ingest", str(EXAMPLE / "alpha")], 2, "--place-db"),  # no URL, no $FLEETMAP_..._URL
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--bogus"], 2, "unrecognized arguments"),
        (
            ["merge", str(EXAMPLE / "alpha"), "-o", "x", "--place-db", "http://127.0.0.1:9"],
            1,
            "Cannot reach http://127.0.0.1:9/healthz",
        ),
        (["stream", str(EXAMPLE / "alpha"), "--place-db", "http://x", "--speed", "-1"], 2, "speed"),
        # numbers that cannot mean what they ask (an outside tester's: tracebacks before)
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--voxel", "-1"], 2, "--voxel"),
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--voxel", "nan"], 2, "--voxel"),
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--voxel", "1e-12"], 2, "--voxel"),
        # robots named wrong (an outside tester's: the working folder read, "File name too
        # long", one folder merged with itself as the identity)
        (["merge", "A=", f"B={EXAMPLE / 'alpha'}", "-o", "x"], 1, "no robot folder after '='"),
        (["merge", f"{'a' * 300}={EXAMPLE / 'alpha'}", "-o", "x"], 1, "Robot id must match"),
        (
            ["merge", f"A={EXAMPLE / 'alpha'}", f"B={EXAMPLE / 'alpha'}/", "-o", "x"],
            1,
            "is given twice (A and B)",
        ),
        (["map", "--place-db", "http://127.0.0.1:9", "-o", "x", "--voxel", "1e-4"], 2, "--voxel"),
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--max-views", "0"], 2, "--max-views"),
        (  # it was "went away before it was ready": the place database's start failed
            ["merge", str(EXAMPLE / "alpha"), "--vocab", "nowhere.npz", "-o", "x"],
            1,
            "Cannot read vocabulary nowhere.npz",
        ),
        (["overlaps", "a", "b", "--place-db", "http://127.0.0.1:9", "--wait", "nan"], 2, "--wait"),
        (["serve", "place-db", "--port", "99999"], 2, "--port"),
        (["vocab", "train", "x", "-o", "y", "--words", "0"], 2, "--words"),
        (["vocab", "train", "x", "-o", "y", "--stride", "-1"], 2, "--stride"),
        (["simulate", "x", "--frames", "0"], 2, "--frames"),
        (["simulate", "x", "--seed", "-5"], 2, "--seed"),  # was numpy's traceback
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--fx", "nan"], 2, "--fx"),  # was 1
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--depth-scale", "0"], 2, "--depth-scale"),
        (  # both stored as one robot x
            [
                "ingest",
                f"x={EXAMPLE / 'alpha'}",
                f"x={EXAMPLE / 'bravo'}",
                "--place-db",
                "http://x",
            ],
            1,
            "Robot ids must differ",
        ),
        (["overlaps", "a", "b", "--place-db", "http://x", "--wait", "1e12"], 2, "--wait"),
        (  # it trained, then failed on the missing folder: checked first now
            [
                "vocab",
                "train",
                str(ROOT / "examples" / "fr1_rpy_fleet" / "alpha"),
                "-o",
                "/etc/hostname/site.npz",
            ],
            1,
            "-o /etc/hostname/site.npz: cannot write there",
        ),  # fmt: skip
        (["extract", str(EXAMPLE / "alpha"), "-o", "x", "--kf-rotation", "nan"], 2, "rotation"),
        (["stream", "nowhere", "--place-db", "http://127.0.0.1:9"], 1, "Robot folder not found"),
        (
            [
                "stream",
                f"x={EXAMPLE / 'alpha'}",
                f"x={EXAMPLE / 'bravo'}",
                "--place-db",
                "http://x",
            ],
            1,
            "Robot ids must differ",
        ),
        (["stream", str(EXAMPLE / "alpha"), "--place-db", "http://127.0.0.1:9"], 1, "127.0.0.1:9"),
        (["map", "--place-db", "http://127.0.0.1:9", "-o", "/etc/hostname"], 1, "not a folder"),
        (["map", "--place-db", "http://127.0.0.1:9", "-o", "x"], 1, "127.0.0.1:9"),
    ],
)
def test_mistakes_end_in_one_line_and_the_right_exit_code(args, code, message):
    r = _run(*args)
    assert r.returncode == code, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr


def test_an_out_folder_holding_a_report_json_folder_stops_before_the_merge(tmp_path):
    """The merge ran whole, wrote the other files, then failed on report.json ("Is a
    directory")."""
    (tmp_path / "report.json").mkdir()
    r = _run("merge", str(EXAMPLE / "alpha"), str(EXAMPLE / "bravo"), "-o", str(tmp_path))
    assert r.returncode == 1 and "report.json is a folder" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "merged.ply").exists()


def test_serve_on_a_taken_port_says_so_in_one_line():
    """It logged "listening on" the port, then uvicorn's "[Errno 98]" and exit 3 (an outside
    tester's review)."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = _run("serve", "aligner", "--port", str(port))
    assert r.returncode == 1, r.stderr
    assert f"cannot listen on 127.0.0.1:{port}" in r.stderr and "listening" not in r.stderr


@pytest.mark.parametrize(
    ("variable", "value", "named"),
    [
        ("FLEETMAP_ALIGNER_ALIGN__FAR_DEPTH_M", "far", "ALIGN__FAR_DEPTH_M"),
        ("FLEETMAP_ALIGNER_ALIGN__FAR_DEPTH_M", "0.5", "far_depth_m"),  # nearer than 1 m
        ("FLEETMAP_PLACE_DB_MAX_BODY_BYTES", "lots", "MAX_BODY_BYTES"),
    ],
)
def test_a_setting_the_embedded_services_cannot_read_is_one_line_naming_it(
    tmp_path, variable, value, named
):
    """`fleetmap merge` starts both services in its own process; a setting of theirs that
    cannot be read ends the job in one line naming it (it was pydantic's four), as
    `fleetmap serve` says it."""
    robots = [str(EXAMPLE / r) for r in ("alpha", "bravo")]
    r = _run("-q", "merge", *robots, "-o", str(tmp_path / "out"), env={variable: value})
    assert r.returncode == 1, r.stderr
    # the example's folders say they take the TUM defaults (no camera.json), in lines apart
    (line,) = [ln for ln in r.stderr.strip().splitlines() if " WARNING " not in ln]
    assert line.startswith("fleetmap: error: setting ") and named in line, line


def test_service_urls_from_the_environment(tmp_path):
    """FLEETMAP_PLACE_DB_URL stands in for --place-db."""
    r = _run("ingest", str(EXAMPLE / "alpha"), env={"FLEETMAP_PLACE_DB_URL": "http://127.0.0.1:9"})
    assert r.returncode == 1 and "Cannot reach http://127.0.0.1:9" in r.stderr


def test_every_command_sends_the_token_to_secured_services(tmp_path, capsys, monkeypatch):
    """`fleetmap --token T merge --place-db URL` never sent it: the place database said 401.
    Now merge, ingest, overlaps and align each send it (from --token or FLEETMAP_TOKEN),
    and each is refused in one line without it."""
    env = {
        "FLEETMAP_PLACE_DB_OPERATOR_TOKEN": "op-secret",
        "FLEETMAP_ALIGNER_OPERATOR_TOKEN": "op-secret",
    }
    db = Service("place-db", tmp_path / "db", env=env).start()
    al = Service("aligner", env=env).start()
    try:
        out = tmp_path / "out"
        common = [str(EXAMPLE / "alpha"), str(EXAMPLE / "bravo"), "-o", str(out)]
        urls = ["--place-db", db.url, "--aligner", al.url]
        assert main(["-q", "merge", *common, *urls]) == 1  # no token: refused, one line
        assert "Bearer" in capsys.readouterr().err
        assert main(["--token", "op-secret", "-q", "merge", *common, *urls]) == 0
        report = json.loads((out / "report.json").read_text())
        assert report["unmerged"] == []
        robots = [str(EXAMPLE / "alpha"), str(EXAMPLE / "bravo")]
        for cmd in (
            ["ingest", *robots, "--place-db", db.url],
            ["overlaps", "alpha", "bravo", "--json", "--place-db", db.url],
            ["align", *robots, "--json", *urls],
        ):
            monkeypatch.delenv("FLEETMAP_TOKEN", raising=False)
            assert main(["-q", *cmd]) == 1, cmd
            assert "Bearer" in capsys.readouterr().err
            assert main(["--token", "op-secret", "-q", *cmd]) == 0, cmd
            monkeypatch.setenv("FLEETMAP_TOKEN", "op-secret")
            assert main(["-q", *cmd]) == 0, cmd
        capsys.readouterr()
    finally:
        db.stop()
        al.stop()
    assert Path(out / "merged.ply").stat().st_size > 0


def test_clients_retry_a_503_and_honour_retry_after():
    """A service that answers 503 (Retry-After: 1) once, then 200: the client's call
    succeeds; a refused connection is retried too, then reported in one line."""
    import http.server
    import threading
    import time

    from fleetmap.client import PlaceDBClient
    from fleetmap.errors import Unavailable

    hits = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (the stdlib's name)
            hits.append(time.monotonic())
            busy = len(hits) == 1
            body = b'{"detail": "busy"}' if busy else b'{"status": "ok"}'
            self.send_response(503 if busy else 200)
            if busy:
                self.send_header("retry-after", "1")
            self.send_header("content-type", "application/json")
            self.send_header("content-length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with PlaceDBClient(f"http://127.0.0.1:{server.server_port}") as c:
            assert c.health() == {"status": "ok"}
        assert len(hits) == 2 and hits[1] - hits[0] >= 0.9  # waited as told
    finally:
        server.shutdown()
    with PlaceDBClient("http://127.0.0.1:9") as c, pytest.raises(Unavailable, match="Cannot reach"):
        c.health()


def test_tokens_from_a_secrets_folder(tmp_path):
    """Tokens as files (Docker secrets, FLEETMAP_SECRETS_DIR): a real service reads its
    operator token from one, and refuses requests without it."""
    secrets = tmp_path / "secrets"
    secrets.mkdir()
    (secrets / "fleetmap_place_db_operator_token").write_text("from-a-file\n")
    env = {"FLEETMAP_SECRETS_DIR": str(secrets)}
    svc = Service("place-db", tmp_path / "db", env=env).start()
    try:
        assert http.get(svc.url + "/robots").status_code == 401
        ok = http.get(svc.url + "/robots", headers={"authorization": "Bearer from-a-file"})
        assert ok.status_code == 200
        assert "from-a-file" not in svc.read_log()
    finally:
        svc.stop()


def test_simulate_refuses_a_folder_holding_an_earlier_run(tmp_path, capsys):
    """A one-robot run into a two-robot run's folder left robot1 beside a T_true.json that
    lists robot0 alone (session 59's outside tester)."""
    out = tmp_path / "sim"
    assert main(["-q", "simulate", str(out), "--robots", "2", "--frames", "2"]) == 0
    assert main(["-q", "simulate", str(out), "--robots", "1", "--frames", "2"]) == 1
    assert "is not empty: give a new or empty folder" in capsys.readouterr().err
    assert set(json.loads((out / "T_true.json").read_text())) == {"robot0", "robot1"}


def test_a_folder_whose_name_is_no_robot_id_is_told_to_name_it(tmp_path, capsys):
    """'robot 1' failed where its first keyframe was encoded, without the way out that
    merge's duplicate ids give (NAME=DIR; session 59's outside tester)."""
    import shutil

    robot = tmp_path / "robot 1"
    shutil.copytree(EXAMPLE / "alpha", robot)
    assert main(["-q", "extract", str(robot), "-o", str(tmp_path / "o")]) == 1
    assert f"(the folder's name): give one, as NAME={robot}" in capsys.readouterr().err
    assert main(["-q", "extract", f"r1={robot}", "-o", str(tmp_path / "o")]) == 0
