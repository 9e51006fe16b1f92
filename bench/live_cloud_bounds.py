"""What the live map's cloud costs for a robot posting large views (issue 26.3): 24 views of
4096x3072 (the fr1 alpha view scaled up, within the view limits), each view's share of the
cloud as the live map took it before (full decode) and now (`view_cloud`, decoded at most
640x480), then the robot's bounded cloud. Prints seconds and the process's peak RSS.

    .venv/bin/python bench/live_cloud_bounds.py [old|new]
"""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from fleetmap.dataset import read_recording
from fleetmap.extract_pool import CLOUD_MAX_DEPTH_M, CLOUD_STRIDE
from fleetmap.fleet.map_render import bounded_voxels, view_cloud
from fleetmap.fleet.view_choice import load_view
from fleetmap.mapcloud import view_points
from fleetmap.view import StoredView, encode_view

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fr1_pair" / "alpha"


def main(how: str, n: int = 24) -> None:
    rec = read_recording(EXAMPLE)
    v, k, s = load_view(rec, 0), rec.intrinsics, 6.4
    big_k = replace(k, fx=k.fx * s, fy=k.fy * s, cx=k.cx * s, cy=k.cy * s, width=4096, height=3072)
    rgb = cv2.resize(v.rgb, (4096, 3072))
    depth = cv2.resize(v.depth, (4096, 3072), interpolation=cv2.INTER_NEAREST)
    enc = encode_view(rgb, depth)
    del rgb, depth
    views = []
    for i in range(n):  # each view moved 0.5 m along x: clouds that do not coincide
        T = v.T_map_cam.copy()
        T[0, 3] += 0.5 * i
        views.append(StoredView(enc, big_k, T, float(i)))
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t = time.perf_counter()
    parts = []
    for sv in views:
        if how == "old":
            d = sv.decoded()
            parts.append(
                view_points(
                    d.rgb, d.depth, d.intrinsics, d.T_map_cam, CLOUD_STRIDE, CLOUD_MAX_DEPTH_M
                )
            )
        else:
            parts.append(view_cloud(sv))
    raw = sum(len(p) for p, _ in parts)
    pts, _ = bounded_voxels(*(np.concatenate(x) for x in zip(*parts, strict=True)))
    dt = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"{how}: {n} views of 4096x3072 ({len(enc['rgb']) / 1e6:.1f} + "
        f"{len(enc['depth']) / 1e6:.1f} MB each): {raw} raw points, {len(pts)} kept, "
        f"{dt:.1f} s, peak RSS {peak:.0f} MB ({peak - base:+.0f} MB over the set-up)"
    )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "new")
