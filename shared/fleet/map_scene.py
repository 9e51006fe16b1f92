"""What the operator page's 3D view draws: each placed robot's map cloud in a compact binary
layout, and the scene's lines (keyframe tracks, verified overlaps) in the reference frame.

The cloud of a robot is in ITS OWN map frame (the page applies `transforms[R]` from
`GET /map`), so a new placement moves it without a download; it is cached per robot until
the robot gains views. A drift-corrected robot's map is bent, so no one transform places
it: its cloud is asked for in the reference frame, each point moved with the keyframe that
saw it (`StoredCorrection.warp`, as `GET /map/cloud.ply`), cached until the next solve.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from fleetmap.fleet.types import transform_from_json
from fleetmap.geometry import apply

#: At most this many points per robot: 15 bytes each, 1.5 MB (the page's budget is 2 MB)
MAX_POINTS = 100_000
DEFAULT_VOXEL_M = 0.02


def cloud_bytes(points: np.ndarray, colours: np.ndarray) -> bytes:
    """The binary cloud: N float32 x y z (little-endian) then N uint8 r g b, so a browser
    reads both as typed arrays without copying. points: ndarray of shape (N, 3) in metres,
    colours: uint8 ndarray of shape (N, 3)."""
    if points.shape != colours.shape or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"Expected points and colours of shape (N, 3), got {points.shape}")
    xyz = np.ascontiguousarray(points, "<f4").tobytes()
    return xyz + np.ascontiguousarray(colours, np.uint8).tobytes()


def thinned(points: np.ndarray, colours: np.ndarray, max_points: int = MAX_POINTS):
    """At most `max_points` of them, evenly spread over the cloud (a fixed stride)."""
    if len(points) <= max_points:
        return points, colours
    keep = np.linspace(0, len(points) - 1, max_points).astype(int)
    return points[keep], colours[keep]


class SceneCache:
    """Binary robot clouds cached by (robot, views, voxel); the renderer builds them."""

    def __init__(self, renderer, max_entries: int = 64):
        self.renderer = renderer
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple, bytes] = OrderedDict()
        self._max = max_entries

    def robot_cloud(self, robot: str, views: int, voxel: float, m: dict | None = None) -> bytes:
        """The robot's cloud voxelised at `voxel` and thinned: in its own map frame, or with
        `m` (the map document, the robot placed in it) in the reference frame, drift-corrected
        where the keyframe graph solved on this placement corrects it."""
        from fleetmap.fleet.live_graph import stored_corrections
        from fleetmap.fleet.map_render import in_reference, solved_at
        from fleetmap.mapcloud import MapCloud

        key = (robot, views, round(voxel, 4))
        if m is not None:
            key += (m["version"], solved_at(m))
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        with self.renderer._lock:
            p, c = self.renderer.robot_cloud(robot)
        if len(p) and voxel > DEFAULT_VOXEL_M:
            p, c = MapCloud(p, c).voxelised(voxel)
        if m is not None:
            p = in_reference(m, robot, p, stored_corrections(self.renderer.db, m["version"])[0])
        body = cloud_bytes(*thinned(p, c))
        with self._lock:
            self._cache[key] = body
            while len(self._cache) > self._max:
                self._cache.popitem(last=False)
        return body


def overlap_lines(db, renderer, m: dict) -> list[list]:
    """Each verified overlap between two placed robots as [robot_a, robot_b, xa, ya, za,
    xb, yb, zb]: the two keyframes' camera positions in the reference frame."""
    T_ref = {r: transform_from_json(T) for r, T in m["transforms"].items()}
    lines = []
    for e in m["overlaps"]:
        a, b = e["robot_a"], e["robot_b"]
        if a not in T_ref or b not in T_ref:
            continue
        for o in db.overlaps(a, b):
            if o.source != "cascade":
                continue
            (_, Pa), (_, Pb) = renderer.pose(o.kf_a), renderer.pose(o.kf_b)
            if Pa is None or Pb is None:
                continue
            pa = apply(T_ref[a], Pa[:3, 3][None])[0]
            pb = apply(T_ref[b], Pb[:3, 3][None])[0]
            lines.append([a, b, *np.round(pa, 4).tolist(), *np.round(pb, 4).tolist()])
    return lines
