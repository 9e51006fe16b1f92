"""The command line as a new user meets it: conventions, one-line errors, exit codes, and
the token reaching secured services from every command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import main
from tests.servers import ROOT, Service

EXAMPLE = ROOT / "examples" / "fr1_pair"


def _run(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    import os

    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
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
        (["merge", str(EXAMPLE / "alpha"), "-o", "/etc/hostname"], 1, "is not a folder"),
        (["ingest", str(EXAMPLE / "alpha")], 2, "--place-db"),  # no URL, no $FLEETMAP_..._URL
        (["merge", str(EXAMPLE / "alpha"), "-o", "x", "--bogus"], 2, "unrecognized arguments"),
        (
            ["merge", str(EXAMPLE / "alpha"), "-o", "x", "--place-db", "http://127.0.0.1:9"],
            1,
            "Cannot reach http://127.0.0.1:9/healthz",
        ),
    ],
)
def test_mistakes_end_in_one_line_and_the_right_exit_code(args, code, message):
    r = _run(*args)
    assert r.returncode == code, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr


def test_service_urls_from_the_environment(tmp_path):
    """FLEETMAP_PLACE_DB_URL stands in for --place-db."""
    r = _run("ingest", str(EXAMPLE / "alpha"), env={"FLEETMAP_PLACE_DB_URL": "http://127.0.0.1:9"})
    assert r.returncode == 1 and "Cannot reach http://127.0.0.1:9" in r.stderr


def test_merge_sends_the_token_to_secured_services(tmp_path, capsys):
    """`fleetmap --token T merge --place-db URL` never sent it: the place database said 401."""
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
    finally:
        db.stop()
        al.stop()
    assert Path(out / "merged.ply").stat().st_size > 0
