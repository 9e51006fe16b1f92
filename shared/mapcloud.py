"""Map clouds from RGB-D keyframes, ICP and PLY output (Open3D)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetmap.camera import backproject_pixels, depth_to_points
from fleetmap.geometry import apply, invert
from fleetmap.lazy import LazyModule

o3d = LazyModule("open3d")

#: Depth readings farther than this (metres) stay out of the map clouds (the aligner's may
#: reach farther in a large scene: `AlignParams.cloud_depth_cap`).
MAX_DEPTH_M = 6.0

REG = LazyModule("open3d", "pipelines.registration")
#: Open3D's random generator is one per process: a seed and the RANSAC drawing from it run
#: under this lock, so two requests' RANSACs at once give what each gives alone
SEEDED = threading.Lock()

ROBOT_COLOURS = np.array(
    [
        [0.85, 0.25, 0.2],
        [0.2, 0.45, 0.9],
        [0.3, 0.7, 0.3],
        [0.9, 0.7, 0.1],
        [0.6, 0.3, 0.8],
        [0.1, 0.7, 0.8],
        [0.9, 0.4, 0.6],
        [0.5, 0.5, 0.5],
    ]
)


@dataclass
class MapCloud:
    """One robot's map cloud from all its keyframes, as extracted (not yet voxelised).

    points : ndarray of shape (N, 3) float32 or float64, robot's map frame (metres).
    colours : ndarray of shape (N, 3) uint8, RGB, or None.
    """

    points: np.ndarray
    colours: np.ndarray | None

    @classmethod
    def from_keyframes(cls, keyframes) -> MapCloud:
        return cls(
            np.concatenate([k.points for k in keyframes]),
            np.concatenate([k.colours for k in keyframes]),
        )

    def o3d(self, voxel: float, normals: bool = True) -> o3d.geometry.PointCloud:
        """Voxel down-sampled Open3D cloud with colours in 0..1 (and normals)."""
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points.astype(np.float64)))
        if self.colours is not None:
            pc.colors = o3d.utility.Vector3dVector(self.colours / 255.0)
        pc = pc.voxel_down_sample(voxel)
        if normals:
            with_normals(pc, voxel)
        return pc

    def voxelised(self, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (M, 3) float64 and colours (M, 3) uint8, one per occupied voxel."""
        pc = self.o3d(voxel, normals=False)
        cols = np.round(np.asarray(pc.colors) * 255).astype(np.uint8)
        return np.asarray(pc.points), cols


def with_normals(pc: o3d.geometry.PointCloud, voxel: float) -> o3d.geometry.PointCloud:
    """`pc` (voxelised at `voxel`) given normals, in place, where it has none yet: the
    local plane of its points within three voxels (at most 30). A cloud made bare (an ICP
    source: point-to-plane and coloured ICP read the target's normals alone) is completed
    so when it is needed as a target, as if made with them."""
    if not pc.has_normals():
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    return pc


def view_points(
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics,
    T_map_cam: np.ndarray,
    stride: int = 4,
    max_depth: float = MAX_DEPTH_M,
) -> tuple[np.ndarray, np.ndarray]:
    """One RGB-D view's share of its robot's map cloud: every `stride`-th pixel with depth
    under `max_depth`, as points of shape (M, 3) float64 in the map frame and their colours
    of shape (M, 3) uint8 RGB (grey repeated)."""
    p, uv = depth_to_points(depth, intrinsics, stride=stride, max_depth=max_depth)
    rgb = rgb if rgb.ndim == 3 else np.repeat(rgb[..., None], 3, axis=2)
    return apply(T_map_cam, p), np.ascontiguousarray(rgb[uv[:, 1], uv[:, 0], ::-1])


def views_cloud(
    views: Iterable,
    voxel: float = 0.03,
    stride: int = 4,
    max_depth: float = MAX_DEPTH_M,
    with_color: bool = True,
) -> o3d.geometry.PointCloud:
    """One robot's map cloud from its RGB-D views: back-projected, voxel down-sampled,
    with normals. Views need rgb, depth, intrinsics and T_map_cam."""
    cloud = ViewsCloud(views, stride, max_depth).raw
    if not with_color:
        cloud = MapCloud(cloud.points, None)
    return cloud.o3d(voxel)


class ViewsCloud:
    """Views back-projected once (every `stride`-th pixel), voxelised clouds with normals
    made on demand and kept per voxel size: the aligner looks at the same views at three
    or four scales."""

    def __init__(self, views: Iterable, stride: int = 4, max_depth: float = MAX_DEPTH_M):
        self.views, self.stride, self.max_depth = list(views), stride, max_depth
        parts = [
            view_points(v.rgb, v.depth, v.intrinsics, v.T_map_cam, stride, max_depth)
            for v in self.views
        ]
        self.raw = MapCloud(
            np.concatenate([p for p, _ in parts]), np.concatenate([c for _, c in parts])
        )
        self._at: dict[float, o3d.geometry.PointCloud] = {}
        self._off_edges: dict[float, np.ndarray] = {}

    def at(self, voxel: float, normals: bool = True) -> o3d.geometry.PointCloud:
        """The cloud at `voxel`, with normals unless `normals` is False (a cloud only
        moved onto another or only counted; `with_normals`): they are most of a cloud's
        cost (`MapCloud.o3d` was 2.7 of 6.0 sampled s of a three-robot merge's alignments)."""
        pc = self._at.get(voxel)
        if pc is None:
            pc = self._at[voxel] = self.raw.o3d(voxel, normals=False)
        return with_normals(pc, voxel) if normals else pc

    def off_edges(self, voxel: float) -> np.ndarray:
        """The points (N, 3) at `voxel` of the pixels off depth edges only: a pixel whose
        3x3 neighbourhood has a hole or spans over 5% of its depth (`backproject_pixels`'
        rule) may mix the depths of both sides of the edge (mixed, "flying" pixels: time of
        flight and structured light alike) and float in space its own camera saw empty."""
        if voxel not in self._off_edges:
            parts = [off_edge_points(v, self.stride, self.max_depth) for v in self.views]
            cloud = MapCloud(np.concatenate(parts), None).o3d(voxel, normals=False)
            self._off_edges[voxel] = np.asarray(cloud.points)
        return self._off_edges[voxel]


def off_edge_points(view, stride: int = 4, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """One view's every `stride`-th pixel off depth edges (`ViewsCloud.off_edges`' rule),
    as points of shape (M, 3) in the map frame."""
    p, uv = depth_to_points(view.depth, view.intrinsics, stride, max_depth)
    ok = backproject_pixels(uv, view.depth, view.intrinsics, max_depth)[1]
    return apply(view.T_map_cam, p[ok])


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


def write_ply(
    path, points: np.ndarray, colors: np.ndarray | None = None, robot: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY: points (N, 3) as float32 x y z, colours (N, 3) as uchar
    red green blue (given in 0..1 floats or uint8), and optionally a per-point `robot`
    index (uint16) that CloudCompare, PCL and Open3D's tensor reader show as a scalar field
    (Open3D's reader skipped it as "ushort", the same type under its older name)."""
    Path(path).write_bytes(ply_bytes(points, colors, robot))


def ply_bytes(
    points: np.ndarray, colors: np.ndarray | None = None, robot: np.ndarray | None = None
) -> bytes:
    """Binary PLY file contents (see `write_ply`)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"Expected points of shape (N, 3), got {points.shape}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    props = ["float x", "float y", "float z"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["uchar red", "uchar green", "uchar blue"]
    if robot is not None:
        fields.append(("robot", "<u2"))
        props.append("uint16 robot")
    rows = np.empty(len(points), dtype=fields)
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
    if colors is not None:
        c = np.asarray(colors)
        c = c if c.dtype == np.uint8 else np.clip(np.round(c * 255), 0, 255).astype(np.uint8)
        for k, name in enumerate(("red", "green", "blue")):
            rows[name] = c[:, k]
    if robot is not None:
        rows["robot"] = robot
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {p}" for p in props] + ["end_header"]
    return ("\n".join(header) + "\n").encode() + rows.tobytes()


def write_pcd(path, points: np.ndarray, colors: np.ndarray, robot: np.ndarray) -> None:
    """Binary PCD v0.7 (PCL's format): x y z float32, rgb packed as PCL does (0x00RRGGBB,
    uint32), and the per-point `robot` index (uint16). Colours (N, 3) uint8 RGB."""
    points = np.asarray(points)
    rows = np.empty(
        len(points),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("robot", "<u2")],
    )
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
    c = np.asarray(colors, np.uint32)
    rows["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    rows["robot"] = robot
    n = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format (fleetmap)\nVERSION 0.7\n"
        "FIELDS x y z rgb robot\nSIZE 4 4 4 4 2\nTYPE F F F U U\nCOUNT 1 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    Path(path).write_bytes(header.encode() + rows.tobytes())


class SeenDepth:
    """What one RGB-D view saw, for the free-space test: its depth in metres, its
    camera-from-map pose, and (made on demand, kept) the nearest reading within 2^k pixels
    of every pixel, k = 0..6, invalid readings never the nearest."""

    RADII = (0, 1, 2, 4, 8, 16, 32, 64)

    def __init__(self, view):
        self.intrinsics = view.intrinsics
        self.T_cam_map = invert(view.T_map_cam)
        self.depth = view.depth.astype(np.float32) / np.float32(view.intrinsics.depth_scale)
        self._nearest = {0: np.where(self.depth > 0, self.depth, np.float32(np.inf))}

    def nearest(self, k: int) -> np.ndarray:
        """Nearest reading (metres) within RADII[k] pixels, shape (H, W) float32."""
        if k not in self._nearest:
            import cv2

            size = 2 * self.RADII[k] + 1
            self._nearest[k] = cv2.erode(
                self._nearest[0],
                cv2.getStructuringElement(cv2.MORPH_RECT, (size, size)),
                borderType=cv2.BORDER_CONSTANT,
                borderValue=float("inf"),
            )
        return self._nearest[k]

    def read(self, points: np.ndarray) -> tuple[np.ndarray, ...]:
        """Points of shape (N, 3) in the map frame as this view sees them: each one's depth
        z along the camera's axis, its pixel (u, w), and the depth d this view read there
        (metres; 0 where it read none, or the point lies behind the camera or outside the
        image)."""
        p = points @ self.T_cam_map[:3, :3].T + self.T_cam_map[:3, 3]
        z = p[:, 2]
        front = z > 0.1
        uv = np.round(self.intrinsics.project(np.where(front[:, None], p, 1.0))).astype(np.int64)
        u, w = uv[:, 0], uv[:, 1]
        h, wd = self.depth.shape
        ok = front & (u >= 0) & (u < wd) & (w >= 0) & (w < h)
        d = np.zeros(len(p))
        d[ok] = self.depth[w[ok], u[ok]]
        return z, d, u, w


def free_space_check(
    points: np.ndarray,
    views: Iterable,
    margin: float = 0.05,
    rel_margin: float = 0.02,
    floor: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[int, int, int]:
    """How well points (N, 3), in the views' map frame, agree with what the views' depth saw.

    Each point is projected into each view. Where that view measured a surface at about the
    point's depth (within tol = `margin` + `rel_margin` x depth) the point is supported;
    where the view saw farther than the point by more than tol, the point sits in space the
    camera saw empty: a conflict. Points behind the measured surface or outside the image
    tell nothing. A wrong alignment of two maps of a look-alike room overlaps surfaces in
    places but puts others in seen-empty space; a right one has few conflicts (Huber and
    Hebert's free-space test).

    A conflict is *firm* where the view saw farther at every pixel within tol of the point
    sideways too (tol x focal / depth pixels, rounded down to a power of two): judged along
    the ray alone, a right point beside a depth edge, moved a few pixels by the maps' own
    pose error, lands in front of the background. Right alignments of SUN3D's two
    recordings (ground truth good to 1.5 deg) had 23-25% conflicts, 1-2% firm ones; maps
    that bend (drift) and look-alike places keep more firm ones (docs/ALIGNER.md).

    `views`: RGB-D views or their `SeenDepth` (which keep the nearest-reading images between
    calls). `floor`: tol at least floor(depth read), the readings' noise at their depths
    (`fleetmap.depth_noise.DepthNoise`). Returns (supports, conflicts, firm conflicts)
    summed over views."""
    support = conflict = firm = 0
    pts = np.asarray(points, np.float64)
    for v in views:
        seen = v if isinstance(v, SeenDepth) else SeenDepth(v)
        z, d, u, w = seen.read(pts)
        ok = d > 0
        tol = margin + rel_margin * d
        if floor is not None:
            tol = np.maximum(tol, floor(d))
        support += int(np.count_nonzero(ok & (np.abs(z - d) <= tol)))
        idx = np.flatnonzero(ok & (z < d - tol))
        conflict += len(idx)
        if not len(idx):
            continue
        radius = tol[idx] * seen.intrinsics.fx / z[idx]
        level = np.searchsorted(SeenDepth.RADII, radius, side="right") - 1
        for k in np.unique(level):
            sel = idx[level == k]
            near = seen.nearest(int(k))[w[sel], u[sel]]
            firm += int(np.count_nonzero(z[sel] < near - tol[sel]))
    return support, conflict, firm
