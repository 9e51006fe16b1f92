"""The live map's cloud from bounded per-view and per-robot clouds (issue 26.3): a view is
decoded for the cloud at most CLOUD_VIEW_PIXELS large, and gives the same geometry."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from fleetmap.dataset import read_recording
from fleetmap.extract_pool import CLOUD_STRIDE
from fleetmap.fleet.map_render import (
    CLOUD_VIEW_PIXELS,
    MAX_ROBOT_POINTS,
    bounded_voxels,
    view_cloud,
)
from fleetmap.fleet.view_choice import load_view
from fleetmap.view import StoredView, encode_view

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


def stored(rgb, depth, intrinsics, T) -> StoredView:
    return StoredView(encode_view(rgb, depth), intrinsics, T, 0.0)


def test_a_large_view_is_decoded_small_and_gives_the_same_geometry():
    rec = read_recording(EXAMPLE / "alpha")
    v = load_view(rec, 0)
    k = rec.intrinsics
    base = view_cloud(stored(v.rgb, v.depth, k, v.T_map_cam))
    s = 6.4  # 640x480 -> 4096x3072, the size the tester posted (within the pixel limit)
    big_k = replace(k, fx=k.fx * s, fy=k.fy * s, cx=k.cx * s, cy=k.cy * s, width=4096, height=3072)
    big = stored(
        cv2.resize(v.rgb, (4096, 3072), interpolation=cv2.INTER_LINEAR),
        cv2.resize(v.depth, (4096, 3072), interpolation=cv2.INTER_NEAREST),
        big_k,
        v.T_map_cam,
    )
    pts, cols = view_cloud(big)
    assert len(pts) <= CLOUD_VIEW_PIXELS / CLOUD_STRIDE**2
    assert len(pts) > 0.5 * len(base[0]) and cols.dtype == np.uint8
    assert np.linalg.norm(pts.mean(0) - base[0].mean(0)) < 0.02  # same surface, within 2 cm
    lo, hi = np.percentile(pts, [5, 95], axis=0), np.percentile(base[0], [5, 95], axis=0)
    assert np.abs(lo - hi).max() < 0.05


def test_a_view_with_absurd_intrinsics_gives_no_far_points():
    """Issue 26.4: fx = fy = 1e-9 stored before the ingest check put points at 1e11 m and
    every later cloud failed in Open3D's voxelisation; such points are left out."""
    rec = read_recording(EXAMPLE / "alpha")
    v = load_view(rec, 0)
    bad = replace(rec.intrinsics, fx=1e-9, fy=1e-9)
    pts, cols = view_cloud(stored(v.rgb, v.depth, bad, v.T_map_cam))
    assert len(pts) < 50 and np.all(np.abs(pts) < 1e4)
    good = view_cloud(stored(v.rgb, v.depth, rec.intrinsics, v.T_map_cam))
    p, _ = bounded_voxels(np.concatenate([pts, good[0]]), np.concatenate([cols, good[1]]))
    assert 0 < len(p) <= MAX_ROBOT_POINTS
