"""The live map under ordinary operator actions and hostile robots (issue 26), in-process on
both backends, with the aligner's real pipeline: a deleted robot leaves nothing behind."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.dataset import read_recording
from fleetmap.extract import FrameExtractor, keyframe_indices
from fleetmap.fleet.merge_worker import LiveMap, LiveParams
from fleetmap.fleet.view_choice import load_view
from fleetmap.frame import decode, encode
from fleetmap.geometry import transform_error
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from fleetmap.view import encode_view
from tests.helpers import moved, post_with_view, real_align

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


def robot_keyframes(vocabulary, robot: str, T_new_old: np.ndarray) -> list:
    """[(encoded frame, view)] of a bundled robot whose map frame is `T_new_old` away."""
    x, rec = FrameExtractor(vocabulary), read_recording(EXAMPLE / robot)
    out = []
    for i in keyframe_indices(rec):
        v = load_view(rec, i)
        f = x(robot, v.stamp, v.rgb, v.depth, rec.intrinsics, T_new_old @ v.T_map_cam)
        out.append((encode(f), encode_view(v.rgb, v.depth)))
    return out


@pytest.fixture(params=["sqlite", "postgres"])
def settings(request, tmp_path):
    database = request.getfixturevalue("pg_url") if request.param == "postgres" else None
    return Settings(data_dir=tmp_path, database=database, max_view_bytes=2_000_000)


def post_bundled_pair(client, vocabulary) -> None:
    """alpha's and bravo's keyframes with their views, both in their own map frames."""
    for robot in ("alpha", "bravo"):
        for frame, view in robot_keyframes(vocabulary, robot, np.eye(4)):
            post_with_view(client, robot, frame, view)


def test_a_deleted_robot_comes_back_fresh(settings, vocabulary):
    """Issue 26.1: B merged, deleted, then streamed again in a map frame 90 degrees and 5 m
    away. The delete removes the pair state, the placement and the link at once; B is not
    placed on the stale fit, and the next alignment places it within 5 cm / 2 degrees of
    its new truth, with its link overlaps made again."""
    T_ab = np.loadtxt(EXAMPLE / "T_alpha_bravo.txt")
    app, calls = create_app(settings), []
    with TestClient(app) as client:
        post_bundled_pair(client, vocabulary)
        assert client.get("/overlaps", params={"wait": 60}).json()["graph"]
        live = LiveMap(app.state.db, real_align(calls), LiveParams(settle_s=3600))
        assert live.tick() is True
        first = client.get("/map").json()
        assert "bravo" in first["transforms"] and app.state.db.links()
        assert client.delete("/robots/bravo").status_code == 200
        gone = client.get("/map").json()
        assert "bravo" not in gone["transforms"] and gone["pairs"] == []
        assert gone["version"] > first["version"] and app.state.db.links() == []
        S = moved(90, 5.0)
        for frame, view in robot_keyframes(vocabulary, "bravo", S):
            post_with_view(client, "bravo", frame, view)
        assert client.get("/overlaps", params={"wait": 60}).json()["graph"]
        live.tick()  # the place of the new robot (none on a stale fit)
        back = client.get("/map").json()
        assert len(calls) == 2, "B came back: aligned anew, never placed on the stale fit"
        dt, dr = transform_error(np.array(back["transforms"]["bravo"]), T_ab @ np.linalg.inv(S))
        assert dt < 0.05 and dr < 2.0, (dt, dr)
        assert back["version"] > gone["version"]
        assert [(k["robot_a"], k["robot_b"]) for k in app.state.db.links()] == [("alpha", "bravo")]


def test_a_robot_posting_copies_moves_no_one(settings, vocabulary):
    """Issue 26.2: robot evil posts a copy of alpha's keyframe and view with alpha's pose,
    then bravo's with a pose 90 degrees and 5 m off. Its copies are no evidence: evil is
    not placed (the reason on /map), no fit of it places bravo, and bravo is placed by
    its own fit with alpha within 5 cm / 2 degrees of the truth."""
    T_ab = np.loadtxt(EXAMPLE / "T_alpha_bravo.txt")
    app, calls = create_app(settings), []
    with TestClient(app) as client:
        post_bundled_pair(client, vocabulary)
        copies = robot_keyframes(vocabulary, "alpha", np.eye(4))
        copies += robot_keyframes(vocabulary, "bravo", moved(90, 5.0))
        for k, (frame, view) in enumerate(copies):
            f = decode(frame)
            f.robot_id, f.stamp = "evil", 5000.0 + k
            post_with_view(client, "evil", encode(f), view)
        assert client.get("/overlaps", params={"wait": 60}).json()["graph"]
        live = LiveMap(app.state.db, real_align(calls), LiveParams(settle_s=3600))
        for _ in range(6):
            if not live.tick():
                break
        m = client.get("/map").json()
        assert "evil" not in m["transforms"], m["transforms"]
        why = {u["robot"]: u["reason"] for u in m["unmerged"]}
        assert "repeat" in why["evil"] and "pictures" in why["evil"], why
        dt, dr = transform_error(np.array(m["transforms"]["bravo"]), T_ab)
        assert dt < 0.05 and dr < 2.0, (dt, dr)


def test_a_robot_flooding_copies_starves_no_pair(settings, vocabulary):
    """Issue 26.6: a robot re-posting copies of alpha's keyframe with random poses kept its
    pair due and first in line; alpha-bravo was never tried. Now alpha-bravo is aligned at
    the first step and the flooding robot never reaches the aligner."""
    app, calls = create_app(settings), []
    with TestClient(app) as client:
        post_bundled_pair(client, vocabulary)
        copy, view = robot_keyframes(vocabulary, "alpha", np.eye(4))[0]
        live = LiveMap(app.state.db, real_align(calls), LiveParams(settle_s=3600))
        for k in range(4):  # a few more copies before every step of the worker
            for j in range(3):
                f = decode(copy)
                f.robot_id, f.stamp = "flood", 100.0 * k + j
                f.T_map_cam = moved(37.0 * (3 * k + j), float(k + j)) @ f.T_map_cam
                post_with_view(client, "flood", encode(f), view)
            client.get("/overlaps", params={"wait": 60})
            live.tick()
        pairs = {(p["robot_a"], p["robot_b"]) for p in client.get("/map").json()["pairs"]}
        assert pairs == {("alpha", "bravo")}, pairs
        assert len(calls) == 1 and "bravo" in client.get("/map").json()["transforms"]


def test_the_map_says_why_pairs_wait_without_an_aligner_or_with_one_down(tmp_path, vocabulary):
    """ "overlaps found, alignment pending" stood for the whole outage of an aligner killed
    mid-stream, and for ever on a place database started without one (an outside tester's
    review, session 51). Now /map says which; an aligner that answers again clears it."""
    from fleetmap.errors import Unavailable

    app = create_app(Settings(data_dir=tmp_path, max_view_bytes=2_000_000))
    down = [True]

    def align(pairs):
        if down[0]:
            raise Unavailable("Cannot reach http://127.0.0.1:9/align")
        return real_align([])(pairs)

    with TestClient(app) as client:
        post_bundled_pair(client, vocabulary)
        assert client.get("/overlaps", params={"wait": 60}).json()["graph"]
        why = {u["robot"]: u["reason"] for u in client.get("/map").json()["unmerged"]}
        assert "no merge worker has reported yet" in why["bravo"], why
        params = LiveParams(settle_s=3600, failure_backoff_s=0.2, poll_s=0.05)
        live = LiveMap(app.state.db, align, params)  # the worker as the service runs it
        live.start()
        try:
            why = _reason_when(client, "bravo", "the aligner failed, tried again: ")
            assert "Cannot reach http://127.0.0.1:9/align" in why
            down[0] = False
            end = time.monotonic() + 120
            while "bravo" not in client.get("/map").json()["transforms"]:
                assert time.monotonic() < end, "bravo never placed once the aligner answered"
                time.sleep(0.2)
            assert "aligner_error" not in client.get("/map").json()["worker"]
        finally:
            live.stop()


def _reason_when(client, robot: str, words: str, wait_s: float = 60) -> str:
    """The robot's unmerged reason on /map, once it holds `words` (AssertionError after
    `wait_s`)."""
    end, why = time.monotonic() + wait_s, ""
    while time.monotonic() < end:
        why = {u["robot"]: u["reason"] for u in client.get("/map").json()["unmerged"]}.get(robot)
        if why and words in why:
            return why
        time.sleep(0.1)
    raise AssertionError(f"{robot}'s reason never said {words!r}: {why!r}")
