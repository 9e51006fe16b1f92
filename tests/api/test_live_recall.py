"""Recall in the live map (issue 21), in-process with the aligner's real pipeline: robots
whose keyframes no cascade verifies are aligned once they are quiet, where the bags of
words point."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from fleetmap.dataset import cut_recording, read_recording
from fleetmap.extract import FrameExtractor, keyframe_indices
from fleetmap.fleet.merge_worker import LiveMap, LiveParams
from fleetmap.fleet.view_choice import load_view
from fleetmap.frame import encode
from fleetmap.geometry import apply, transform_error
from fleetmap.services.place_db.config import Settings
from fleetmap.services.place_db.main import create_app
from fleetmap.view import encode_view
from tests.helpers import moved, post_with_view, real_align

pytestmark = pytest.mark.slow


def window(vocabulary, folder, frames: slice, robot_dir, T_new_old: np.ndarray) -> list:
    """[(encoded frame, view)] of the keyframes of a robot cut from a recording's frames,
    its map moved by T_new_old (the robot `fleetmap merge` would see)."""
    rec = read_recording(cut_recording(folder, frames, robot_dir, T_new_old))
    x, out = FrameExtractor(vocabulary), []
    for i in keyframe_indices(rec):
        v = load_view(rec, i)
        f = x(rec.robot_id, v.stamp, v.rgb, v.depth, rec.intrinsics, v.T_map_cam)
        out.append((encode(f), encode_view(v.rgb, v.depth)))
    return out


def test_live_map_tries_an_unverified_pair_once_quiet(hololens, vocabulary, tmp_path):
    """HoloLens walk frames 15-75 of hl_a and of hl_b (sharing half their surfaces, partly
    walked the other way; `fleetmap merge` merges them, tests/e2e/test_recall.py): the
    cascade verifies no pair, so before issue 21 the live map never tried them. Once the
    robots are quiet the worker aligns them from the nominated pairs with every view: a
    merge within 5 cm / 2 deg of the truth, tried once (nothing new: nothing aligned
    again)."""
    S = moved(90, 5.0)  # B's map frame
    T_true = np.loadtxt(hololens / "T_a_b.txt") @ np.linalg.inv(S)  # B's new map into A's
    app, calls = create_app(Settings(data_dir=tmp_path, max_view_bytes=2_000_000)), []
    with TestClient(app) as client:
        for robot, folder, T in (("A", "hl_a", np.eye(4)), ("B", "hl_b", S)):
            keyframes = window(vocabulary, hololens / folder, slice(15, 75), tmp_path / robot, T)
            for frame, view in keyframes:
                post_with_view(client, robot, frame, view)
        cams_b = np.stack([f.T_map_cam[:3, 3] for f in read_recording(tmp_path / "B").frames])
        assert client.get("/overlaps", params={"wait": 120}).json()["graph"] == []
        live = LiveMap(app.state.db, real_align(calls), LiveParams(settle_s=0.0))
        assert live.tick() is True
        m = client.get("/map").json()
        (pair,) = m["pairs"]
        assert pair["views"] == [12, 12] and pair["evidence"] == 0
        T_ref = {r: np.array(T) for r, T in m["transforms"].items()}
        # refused before the sideways free-space tolerance (11 inliers, 12 needed): now the
        # geometry decides, as in `fleetmap merge`
        assert pair["status"] == "merged", pair
        T_fit = np.linalg.inv(T_ref["A"]) @ T_ref["B"]
        # measured at B's cameras: B's map origin lies 5 m away, where 0.4 deg reads 4 cm
        dt = np.linalg.norm(apply(T_fit, cams_b) - apply(T_true, cams_b), axis=1).max()
        dr = transform_error(T_fit, T_true)[1]
        assert dt < 0.05 and dr < 2.0, (dt, dr)
        assert live.tick() is False and len(calls) == 1
