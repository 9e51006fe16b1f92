"""Map clouds from RGB-D keyframes, ICP and PLY output (Open3D)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import open3d as o3d

from shared.camera import depth_to_points
from shared.geometry import apply

REG = o3d.pipelines.registration


def views_cloud(
    views: Iterable,
    voxel: float = 0.03,
    stride: int = 4,
    max_depth: float = 6.0,
    with_color: bool = True,
) -> o3d.geometry.PointCloud:
    """One robot's map cloud from its RGB-D views: back-projected, voxel down-sampled,
    with normals. Views need rgb, depth, intrinsics and T_map_cam."""
    pts, cols = [], []
    for v in views:
        p, uv = depth_to_points(v.depth, v.intrinsics, stride=stride, max_depth=max_depth)
        pts.append(apply(v.T_map_cam, p))
        if with_color and v.rgb.ndim == 3:
            cols.append(v.rgb[uv[:, 1], uv[:, 0], ::-1] / 255.0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts)))
    if cols:
        pc.colors = o3d.utility.Vector3dVector(np.concatenate(cols))
    pc = pc.voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return pc


def icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    distances: tuple[float, ...] = (0.15, 0.06, 0.03),
    iterations: int = 40,
):
    """Coarse-to-fine point-to-plane ICP of source into target from `init`.

    Returns (T 4x4, fitness, inlier rmse) at the finest distance."""
    T = np.asarray(init, np.float64)
    est = (
        REG.TransformationEstimationPointToPlane()
        if target.has_normals()
        else REG.TransformationEstimationPointToPoint()
    )
    res = None
    for d in distances:
        res = REG.registration_icp(
            source, target, d, T, est, REG.ICPConvergenceCriteria(max_iteration=iterations)
        )
        T = res.transformation
    return np.asarray(T), float(res.fitness), float(res.inlier_rmse)


def overlap_fitness(source, target, T: np.ndarray, distance: float) -> float:
    """Share of source points within `distance` of the target after T."""
    return float(REG.evaluate_registration(source, target, distance, T).fitness)


def write_ply(path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary PLY of points (N, 3) with optional colours (N, 3) in 0..1."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if colors is not None:
        pc.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
    o3d.io.write_point_cloud(str(path), pc, write_ascii=False)


def ply_bytes(points: np.ndarray, colors: np.ndarray | None = None) -> bytes:
    """Binary PLY file contents of points (N, 3) and optional colours (N, 3) in 0..1."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "cloud.ply"
        write_ply(path, points, colors)
        return path.read_bytes()


def free_space_check(
    points: np.ndarray, views: Iterable, margin: float = 0.05, rel_margin: float = 0.02
) -> tuple[int, int]:
    """How well points (N, 3), in the views' map frame, agree with what the views' depth saw.

    Each point is projected into each view. Where that view measured a surface at about the
    point's depth (within `margin` + `rel_margin` x depth) the point is supported; where
    the view saw farther, through the point, the point sits in space the camera saw empty:
    a conflict. Points behind the measured surface or outside the image tell nothing.
    A wrong alignment of two maps of a look-alike room overlaps surfaces in places but puts
    others in seen-empty space; a right one has few conflicts (Huber and Hebert's
    free-space test). Returns (supports, conflicts) summed over views.
    """
    support = conflict = 0
    pts = np.asarray(points, np.float64)
    for v in views:
        K = v.intrinsics
        T = np.linalg.inv(v.T_map_cam)
        p = pts @ T[:3, :3].T + T[:3, 3]
        z = p[:, 2]
        front = z > 0.1
        zs = np.where(front, z, 1.0)
        u = np.round(K.fx * p[:, 0] / zs + K.cx).astype(np.int64)
        w = np.round(K.fy * p[:, 1] / zs + K.cy).astype(np.int64)
        h, wd = v.depth.shape
        ok = front & (u >= 0) & (u < wd) & (w >= 0) & (w < h)
        d = np.zeros(len(p))
        d[ok] = v.depth[w[ok], u[ok]] / K.depth_scale
        ok &= d > 0
        tol = margin + rel_margin * d
        support += int(np.count_nonzero(ok & (np.abs(z - d) <= tol)))
        conflict += int(np.count_nonzero(ok & (z < d - tol)))
    return support, conflict
