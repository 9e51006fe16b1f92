"""The live map's merged cloud, keyframe trajectories and overview picture (the files
behind `GET /map/cloud.ply`, `/map/trajectories`, `/map/overview.png`), with per-process
caches of what never changes (a keyframe's pose and its share of the cloud)."""

from __future__ import annotations

import io
import logging
import threading
from collections import OrderedDict

import numpy as np

from fleetmap.extract_pool import CLOUD_MAX_DEPTH_M, CLOUD_STRIDE  # as `fleetmap merge`
from fleetmap.fleet.live_graph import stored_corrections
from fleetmap.fleet.types import transform_from_json
from fleetmap.geometry import apply, pose_to_tum

log = logging.getLogger(__name__)

BASE_VOXEL_M = 0.02  # each robot's cloud is kept at this voxel size, then re-voxelised
# Bounds of what a cloud may cost, whatever the robots post within the view limits:
CLOUD_VIEW_PIXELS = 640 * 480  # a view is decoded for the cloud at most this large
MAX_ROBOT_POINTS = 400_000  # a robot's cached cloud (11 MB), coarser voxels beyond
MAX_CLOUD_POINTS = 2_000_000  # a merged cloud (a 30 MB PLY), coarser voxels beyond
MAX_EXTENT_M = 10_000.0  # points farther from the map origin are no map (bad intrinsics)
# Views decoded per request at most (full-size pixels: about 1.5 s of PNG depth decoding);
# a cloud with more new views fills in over the next requests.
CLOUD_DECODE_PIXELS = 5 * 4096 * 3072


class MapRenderer:
    """The cloud, trajectories and overview of the live map, cached per process."""

    def __init__(self, db, max_cached_robots: int = 64):
        self.db = db
        self._lock = threading.RLock()  # matplotlib and the caches: one at a time
        self._poses: dict[int, tuple[float, np.ndarray | None]] = {}  # id -> stamp, pose
        self._clouds: OrderedDict[str, tuple[set, np.ndarray, np.ndarray]] = OrderedDict()
        self._max_cached = max_cached_robots
        self._overview: tuple[tuple, bytes] | None = None
        self._cloud: tuple[tuple, tuple] | None = None
        self._spent, self.complete = 0, True  # views decoded this request; all in?

    def pose(self, kf_id: int) -> tuple[float, np.ndarray | None]:
        """A keyframe's stamp and camera pose (read once: they never change)."""
        if kf_id not in self._poses:
            f = self.db.load_frame(kf_id)
            self._poses[kf_id] = (f.stamp, f.T_map_cam)
        return self._poses[kf_id]

    def robot_cloud(self, robot: str, fresh: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """One robot's map cloud from its stored views, in its own map frame: points of
        shape (N, 3) float64 and colours (N, 3) uint8 RGB, voxelised at BASE_VOXEL_M (or
        coarser: at most MAX_ROBOT_POINTS). Each view is decoded once per process, at most
        CLOUD_VIEW_PIXELS large, and no more than CLOUD_DECODE_PIXELS of views per call
        (`fresh`; else per cloud request): `self.complete` says whether all are in. A robot
        deleted and posted again starts anew."""
        with self._lock:
            if fresh:
                self._spent, self.complete = 0, True
            ids = self.db.view_ids(robot)
            life = self.db.incarnation(robot)
            empty = (life, set(), np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
            cached = self._clouds.pop(robot, empty)
            _, done, pts, cols = cached if cached[0] == life else empty
            new = self._affordable([k for k in ids if k not in done])
            self.complete = self.complete and len(done) + len(new) == len(ids)
            if new:
                parts = [(pts, cols)] + [self._view_cloud(k) for k in new]
                pts, cols = bounded_voxels(*(np.concatenate(x) for x in zip(*parts, strict=True)))
                done = done | set(new)
            self._clouds[robot] = (life, done, pts, cols)
            while len(self._clouds) > self._max_cached:
                self._clouds.popitem(last=False)
            return pts, cols

    def _affordable(self, new: list[int]) -> list[int]:
        """The first of the new views that fit in what is left of CLOUD_DECODE_PIXELS (at
        least one per call, so every cloud fills in)."""
        out = []
        for k in new:
            info = self.db.load_frame(k)
            if out and self._spent + info.width * info.height > CLOUD_DECODE_PIXELS:
                break
            self._spent += info.width * info.height
            out.append(k)
        return out

    def _view_cloud(self, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """One stored view's share of its robot's cloud (nothing for a view that fails)."""
        from fleetmap.view import stored_view

        try:
            sv = stored_view(self.db.load_frame(kf_id), *self.db.view_bytes(kf_id))
            return view_cloud(sv)
        except Exception as exc:  # a view stored before the checks of today: left out
            log.warning("live map: keyframe %d's view left out of the cloud: %s", kf_id, exc)
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)

    def cloud(self, m: dict, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points in the reference frame, colours (uint8 RGB) and robot index (the order of
        `m["robots"]`) of every placed robot, voxelised at `voxel` per robot (coarser past
        MAX_CLOUD_POINTS in all); the last answer is kept while the map is unchanged."""
        key = (m["version"], tuple(f["views"] for f in m["fleet"]), voxel, solved_at(m))
        with self._lock:
            if self._cloud is not None and self._cloud[0] == key:
                return self._cloud[1]
            placed = [(k, r) for k, r in enumerate(m["robots"]) if r in m["transforms"]]
            self._spent, self.complete = 0, True
            clouds = {r: self.robot_cloud(r, fresh=False) for _, r in placed}
            total = sum(len(p) for p, _ in clouds.values())
            while voxel < 1.0 and total > MAX_CLOUD_POINTS * (voxel / BASE_VOXEL_M) ** 2:
                voxel *= 2  # a voxel twice as large keeps about a quarter of a surface
            pts, cols, idx = [], [], []
            corrected = stored_corrections(self.db, m["version"])[0]
            for k, r in placed:
                p, c = clouds[r]
                if len(p) and voxel > BASE_VOXEL_M:
                    p, c = _voxelised(p, c, voxel)
                pts.append(in_reference(m, r, p, corrected))
                cols.append(c)
                idx.append(np.full(len(p), k, np.uint16))
            out = _joined(pts, cols, idx)
            self._cloud = (key, out) if self.complete else None
            return out

    def trajectories(self, m: dict) -> dict[str, list[list[float]]]:
        """Each placed robot's keyframe poses in the reference frame: [stamp, tx, ty, tz,
        qx, qy, qz, qw] rows (TUM order), in time order; drift-corrected where the
        keyframe graph solved on this placement corrects the robot."""
        out = {}
        corrected = stored_corrections(self.db, m["version"])[0]
        for r, T in m["transforms"].items():
            T_ref_r = transform_from_json(T)
            place = corrected[r].pose if r in corrected else lambda _, P, T=T_ref_r: T @ P
            rows = []
            for kf in self.db.keyframe_ids(r):
                stamp, P = self.pose(kf)
                if P is not None:
                    rows.append([stamp, *pose_to_tum(place(stamp, P)).tolist()])
            out[r] = rows
        return out

    def overview(self, m: dict) -> bytes:
        """overview.png of the live map (cached until the map or its keyframes change)."""
        with self._lock:
            return self._render_overview(m)

    def _render_overview(self, m: dict) -> bytes:
        from fleetmap import pictures
        from fleetmap.mapcloud import ROBOT_COLOURS

        key = (m["version"], tuple(f["views"] for f in m["fleet"]), solved_at(m))
        if self._overview is not None and self._overview[0] == key:
            return self._overview[1]
        pts, _, idx = self.cloud(m, 0.05)
        tracks = self.trajectories(m)
        names = [r for r in m["robots"] if r in m["transforms"]]
        buf = io.BytesIO()
        if not names or not len(pts):
            _empty_picture(buf, m)
        else:
            k_of = {r: k for k, r in enumerate(m["robots"])}
            pictures.overview(
                buf,
                [pts[idx == k_of[r]] for r in names],
                {r: np.array([row[1:4] for row in tracks[r]]).reshape(-1, 3) for r in names},
                names,
                [ROBOT_COLOURS[k_of[r] % len(ROBOT_COLOURS)] for r in names],
                [],
                {},
                title=f"fleetmap live map v{m['version']}: {len(names)} robots placed, "
                f"{len(m['unmerged'])} unmerged\nreference frame: {m['reference']}'s map",
            )
        self._overview = (key, buf.getvalue()) if self.complete else None
        return buf.getvalue()


def solved_at(m: dict) -> float | None:
    """When the keyframe graph the map document shows was solved (None: not yet)."""
    return m.get("fleet_graph", {}).get("solved_at")


def in_reference(m: dict, robot: str, points: np.ndarray, corrected: dict) -> np.ndarray:
    """A placed robot's map points (N, 3) in the reference frame of the map document `m`:
    each moved with its keyframe's drift correction where the robot is corrected
    (`corrected`: `stored_corrections` of m's version), else by `transforms[robot]`."""
    if robot in corrected:
        return corrected[robot].warp(points)
    return apply(transform_from_json(m["transforms"][robot]), points)


def _empty_picture(buf, m: dict) -> None:
    from fleetmap.pictures import _plt

    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ax.text(0.5, 0.5, f"no robot placed yet ({len(m['robots'])} robots known)", ha="center")
    ax.set_axis_off()
    fig.savefig(buf, format="png")
    plt.close(fig)


def view_cloud(view) -> tuple[np.ndarray, np.ndarray]:
    """A stored view's share of its robot's map cloud (`fleetmap.view.StoredView`), as
    `fleetmap merge` takes it (every CLOUD_STRIDE-th pixel under CLOUD_MAX_DEPTH_M) from
    the view decoded at most CLOUD_VIEW_PIXELS large (JPEG colour at 1/2, 1/4 or 1/8 by the
    decoder itself): points (M, 3) float64 in the robot's map frame, colours (M, 3) uint8."""
    from dataclasses import replace

    import cv2

    from fleetmap.mapcloud import view_points
    from fleetmap.view import decode_image

    k = view.intrinsics
    f = 1
    while f < 8 and k.width * k.height > CLOUD_VIEW_PIXELS * f * f:
        f *= 2
    flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2}.get(f)
    flag = flag if flag is not None else getattr(cv2, f"IMREAD_REDUCED_COLOR_{f}")
    rgb = cv2.imdecode(np.frombuffer(view.encoded["rgb"], np.uint8), flag)
    depth = decode_image(view.encoded["depth"], "depth", True)[::f, ::f]
    if rgb is None:
        raise ValueError("colour does not decode")
    h, w = min(rgb.shape[0], depth.shape[0]), min(rgb.shape[1], depth.shape[1])
    small = replace(k, fx=k.fx / f, fy=k.fy / f, cx=k.cx / f, cy=k.cy / f, width=w, height=h)
    pts, cols = view_points(
        rgb[:h, :w], depth[:h, :w], small, view.T_map_cam, CLOUD_STRIDE, CLOUD_MAX_DEPTH_M
    )
    keep = np.all(np.abs(pts) < MAX_EXTENT_M, axis=1)  # also drops NaN and inf
    return pts[keep], cols[keep]


def bounded_voxels(pts: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Voxelised at BASE_VOXEL_M, or at twice that and so on until MAX_ROBOT_POINTS."""
    voxel = BASE_VOXEL_M
    pts, cols = _voxelised(pts, cols, voxel)
    while len(pts) > MAX_ROBOT_POINTS:
        voxel *= 2
        pts, cols = _voxelised(pts, cols, voxel)
    return pts, cols


def _voxelised(pts: np.ndarray, cols: np.ndarray, voxel: float) -> tuple:
    from fleetmap.mapcloud import MapCloud

    if not len(pts):
        return pts, cols
    return MapCloud(pts, cols).voxelised(voxel)


def _joined(pts: list, cols: list, idx: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.uint16)
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(idx)
