"""The robot-side install: `pip install fleetmap` has none of the server's libraries, a robot
extracts, encodes and posts keyframes without them, and a server command on such an install
ends in one line naming the fix."""

from __future__ import annotations

import re
import tomllib

import pytest

from fleetmap.dataset import read_recording
from fleetmap.extract import FrameExtractor, extract_recording
from fleetmap.frame import encode
from fleetmap.lazy import SERVER_FIX
from fleetmap.vocabulary import load_vocabulary
from tests.robot_side import BLOCKED, SERVER_IMPORTS, run_cli, run_python
from tests.servers import ROOT

ROBOT = ROOT / "examples" / "fr1_pair" / "alpha"
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _names(requirements: list[str]) -> set[str]:
    return {re.match(r"[A-Za-z0-9._-]+", r).group(0).lower() for r in requirements}


def test_the_base_dependencies_have_no_server_library():
    base = _names(PROJECT["dependencies"])
    server = _names(PROJECT["optional-dependencies"]["server"])
    for heavy in ("torch", "open3d", "faiss-cpu", "scipy", "fastapi", "uvicorn"):
        assert heavy not in base and heavy in server, heavy
    assert not base & server
    # the robot-side tests below block exactly the server extra's libraries
    assert set(SERVER_IMPORTS) == server


def test_every_full_install_takes_the_server_extra():
    assert '-e ".[server,dev]"' in (ROOT / "scripts" / "install.sh").read_text()


ROBOT_SIDE = """
from pathlib import Path
from fleetmap.client import PlaceDBClient
from fleetmap.dataset import read_recording
from fleetmap.errors import MissingDependency
from fleetmap.extract import FrameExtractor, extract_recording
from fleetmap.frame import decode, encode
from fleetmap.vocabulary import kmeans, load_vocabulary

rec = read_recording(sys.argv[1], "alpha", require_depth=True, require_poses=True)
frames = list(extract_recording(rec, FrameExtractor(load_vocabulary())))
data = encode(frames[0])
assert encode(decode(data)) == data
Path(sys.argv[2]).write_bytes(data)
with PlaceDBClient("http://127.0.0.1:9,http://127.0.0.1:10", timeout=5) as client:
    assert len(client.urls) == 2
try:
    kmeans(decode(data).descriptors, 4)
except MissingDependency as exc:
    print(exc)
loaded = sorted(n for n in sys.modules if n.split(".")[0] in {blocked!r} and sys.modules[n])
print("server modules loaded:", loaded)
"""


def test_a_robot_extracts_and_encodes_keyframes_without_the_server_libraries(tmp_path):
    r = run_python(ROBOT_SIDE.format(blocked=BLOCKED), str(ROBOT), str(tmp_path / "kf.fmf"))
    assert r.returncode == 0, r.stderr
    assert "server modules loaded: []" in r.stdout
    assert f"faiss is not installed: {SERVER_FIX}" in r.stdout
    # the very bytes a full install makes of the same keyframe
    rec = read_recording(ROBOT, "alpha", require_depth=True, require_poses=True)
    frame = next(extract_recording(rec, FrameExtractor(load_vocabulary())))
    assert (tmp_path / "kf.fmf").read_bytes() == encode(frame)


@pytest.mark.parametrize(
    ("args", "missing"),
    [
        (["serve", "place-db", "--port", "1"], "fastapi, uvicorn, scipy, faiss, torch, open3d"),
        (["serve", "aligner"], "fastapi"),
        (["merge", str(ROBOT), "-o", "OUT"], "open3d"),
        (["vocab", "train", str(ROBOT), "-o", "OUT.npz"], "(faiss not installed)"),
        (["simulate", "OUT", "--robots", "1"], "(scipy not installed)"),
    ],
)
def test_a_server_command_on_a_robot_install_says_what_to_install(args, missing, tmp_path):
    command = " ".join(args[:2] if args[0] == "vocab" else args[:1])
    args = [str(tmp_path / a) if a.startswith("OUT") else a for a in args]
    r = run_cli(*args)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith(f"fleetmap: error: fleetmap {command} needs the server")
    assert missing in lines[0] and lines[0].endswith(SERVER_FIX)
    assert not list(tmp_path.iterdir())  # refused before any work


def test_robot_commands_run_on_a_robot_install(tmp_path):
    r = run_cli("-q", "extract", str(ROBOT), "-o", str(tmp_path / "frames"))
    assert r.returncode == 0, r.stderr
    assert len(list((tmp_path / "frames").glob("*.fmf"))) == 1
    # ingest reads, extracts and reaches for the service: a network error, not a library one
    r = run_cli("ingest", str(ROBOT), "--place-db", "http://127.0.0.1:9")
    assert r.returncode == 1 and "Cannot reach http://127.0.0.1:9" in r.stderr, r.stderr
    assert run_cli("--help").returncode == 0
