"""Ground-truth co-visibility of two RGB-D frames of different robots (test helper)."""

from __future__ import annotations

import numpy as np

from fleetmap.camera import Intrinsics, depth_to_points
from fleetmap.dataset import FrameRecord, load_depth
from fleetmap.geometry import apply, invert


def covisibility(
    fa: FrameRecord, fb: FrameRecord, T_a_b: np.ndarray, intr: Intrinsics, tol_m: float = 0.1
) -> float:
    """Fraction of b's depth points that a's camera sees at a consistent depth."""
    pb, _ = depth_to_points(load_depth(fb.depth_path), intr, stride=8)
    pc = apply(invert(fa.T_map_cam) @ T_a_b @ fb.T_map_cam, pb)
    z = pc[:, 2]
    front = z > 0.1
    u = np.round(intr.fx * pc[front, 0] / z[front] + intr.cx).astype(int)
    v = np.round(intr.fy * pc[front, 1] / z[front] + intr.cy).astype(int)
    inside = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    da = load_depth(fa.depth_path).astype(np.float64) / intr.depth_scale
    seen = np.abs(da[v[inside], u[inside]] - z[front][inside]) < tol_m
    return float(seen.sum()) / max(len(pb), 1)
