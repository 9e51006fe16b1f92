"""What the live map shows: the map document (`GET /map`), why a robot is not placed, the
merged cloud, the keyframe trajectories and the overview picture, all read from the store
(any replica answers the same), with per-process caches of what never changes (a keyframe's
pose and its share of the cloud)."""

from __future__ import annotations

import io
import json
import threading
from collections import OrderedDict

import numpy as np

from fleetmap.extract_pool import CLOUD_MAX_DEPTH_M, CLOUD_STRIDE  # as `fleetmap merge`
from fleetmap.geometry import apply, pose_to_tum
from fleetmap.place.live import load_states, read_placement, robot_order

BASE_VOXEL_M = 0.02  # each robot's cloud is kept at this voxel size, then re-voxelised


def map_document(db) -> dict:
    """{"version", "reference", "transforms" (robot: T_ref_robot), "unmerged" [{"robot",
    "reason"}], "robots", "updated_at"} and, for the operator, "fleet" (per robot:
    keyframes, views, state), "pairs" (the merge worker's pair states) and "overlaps"."""
    m = read_placement(db.store)
    robots = db.robots()
    names = robot_order(db, robots)
    states = load_states(db.store)
    graph = db.overlap_graph()
    placed = m.get("transforms", {})
    counts = {r["robot_id"]: r["keyframes"] for r in robots}
    fleet = []
    for r in names:
        n_views = len(db.store.view_ids(db.store.robot_code(r) or -1))
        state = "reference" if r == m.get("reference") else "merged" if r in placed else "unmerged"
        fleet.append({"robot": r, "keyframes": counts.get(r, 0), "views": n_views, "state": state})
    return {
        "version": m.get("version", 0),
        "reference": m.get("reference"),
        "transforms": {r: T for r, T in placed.items() if r in counts},
        "unmerged": [
            {"robot": f["robot"], "reason": unmerged_reason(f, states, graph, placed)}
            for f in fleet
            if f["state"] == "unmerged"
        ],
        "robots": names,
        "updated_at": m.get("updated_at"),
        "fleet": fleet,
        "pairs": sorted(states.values(), key=lambda s: (s["robot_a"], s["robot_b"])),
        "overlaps": graph,
        "worker": _worker(db.store),
    }


def _worker(store) -> dict | None:
    """The merge worker's last word: the pairs it is aligning and how many more wait; None
    before it first ran (or without a worker)."""
    raw = store.live_get("worker")
    return None if raw is None else json.loads(raw)


def unmerged_reason(robot: dict, states: dict, graph: list[dict], placed: dict) -> str:
    """One line: why this robot is not in the map (yet)."""
    r = robot["robot"]
    if robot["views"] == 0:
        return "its keyframes were posted without RGB-D views: they can be queried, not aligned"
    mine = [s for s in states.values() if r in (s["robot_a"], s["robot_b"])]
    merged = [s for s in mine if s["status"] == "merged"]
    if merged:
        others = sorted({s["robot_a"] if s["robot_b"] == r else s["robot_b"] for s in merged})
        return (
            f"merged with {', '.join(others)}, a group that shares no aligned place with "
            "the reference's"
        )
    verified = [e for e in graph if r in (e["robot_a"], e["robot_b"])]
    if not verified:
        return "no verified overlap with another robot yet"
    refused = [s for s in mine if s["status"] in ("refused", "no_views")]
    if refused:
        last = max(refused, key=lambda s: s["at"])
        other = last["robot_a"] if last["robot_b"] == r else last["robot_b"]
        return (
            f"alignment with {other} refused on {last['evidence']} verified overlaps: "
            f"{last['reason']}; tried again when more overlaps are found"
        )
    return "overlaps found, alignment pending"


class MapRenderer:
    """The cloud, trajectories and overview of the live map, cached per process."""

    def __init__(self, db, max_cached_robots: int = 64):
        self.db = db
        self._lock = threading.RLock()  # matplotlib and the caches: one at a time
        self._poses: dict[int, tuple[float, np.ndarray | None]] = {}  # id -> stamp, pose
        self._clouds: OrderedDict[str, tuple[set, np.ndarray, np.ndarray]] = OrderedDict()
        self._max_cached = max_cached_robots
        self._overview: tuple[tuple, bytes] | None = None

    def pose(self, kf_id: int) -> tuple[float, np.ndarray | None]:
        """A keyframe's stamp and camera pose (read once: they never change)."""
        if kf_id not in self._poses:
            f = self.db.load_frame(kf_id)
            self._poses[kf_id] = (f.stamp, f.T_map_cam)
        return self._poses[kf_id]

    def robot_cloud(self, robot: str) -> tuple[np.ndarray, np.ndarray]:
        """One robot's map cloud from its stored views (its own frame), voxelised at
        BASE_VOXEL_M; new keyframes are added to the cached cloud."""
        from fleetmap.mapcloud import MapCloud, view_points
        from fleetmap.view import stored_view

        store = self.db.store
        ids = store.view_ids(store.robot_code(robot) or -1)
        empty = (set(), np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
        done, pts, cols = self._clouds.pop(robot, empty)
        new = [k for k in ids if k not in done]
        if new:
            parts = [(pts, cols)]
            for k in new:
                v = stored_view(self.db.load_frame(k), *self.db.view_bytes(k)).decoded()
                parts.append(
                    view_points(
                        v.rgb, v.depth, v.intrinsics, v.T_map_cam, CLOUD_STRIDE, CLOUD_MAX_DEPTH_M
                    )
                )
            cloud = MapCloud(*(np.concatenate(x) for x in zip(*parts, strict=True)))
            pts, cols = cloud.voxelised(BASE_VOXEL_M)
            done = done | set(new)
        self._clouds[robot] = (done, pts, cols)
        while len(self._clouds) > self._max_cached:
            self._clouds.popitem(last=False)
        return pts, cols

    def cloud(self, m: dict, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points in the reference frame, colours (uint8 RGB) and robot index (the order of
        `m["robots"]`) of every placed robot, voxelised at `voxel` per robot."""
        from fleetmap.mapcloud import MapCloud

        pts, cols, idx = [], [], []
        with self._lock:
            for k, r in enumerate(m["robots"]):
                if r not in m["transforms"]:
                    continue
                p, c = self.robot_cloud(r)
                if len(p) and voxel > BASE_VOXEL_M:
                    p, c = MapCloud(p, c).voxelised(voxel)
                pts.append(apply(np.array(m["transforms"][r]), p))
                cols.append(c)
                idx.append(np.full(len(p), k, np.uint16))
        if not pts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.uint16)
        return np.concatenate(pts), np.concatenate(cols), np.concatenate(idx)

    def trajectories(self, m: dict) -> dict[str, list[list[float]]]:
        """Each placed robot's keyframe poses in the reference frame: [stamp, tx, ty, tz,
        qx, qy, qz, qw] rows (TUM order), in time order."""
        out = {}
        for r, T in m["transforms"].items():
            T = np.array(T)
            rows = []
            for kf in self.db.store.robot_keyframe_ids(self.db.store.robot_code(r) or -1):
                stamp, P = self.pose(kf)
                if P is not None:
                    rows.append([stamp, *pose_to_tum(T @ P).tolist()])
            out[r] = rows
        return out

    def overview(self, m: dict) -> bytes:
        """overview.png of the live map (cached until the map or its keyframes change)."""
        with self._lock:
            return self._render_overview(m)

    def _render_overview(self, m: dict) -> bytes:
        from fleetmap import pictures
        from fleetmap.mapcloud import ROBOT_COLOURS

        key = (m["version"], tuple(f["views"] for f in m["fleet"]))
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
        self._overview = (key, buf.getvalue())
        return self._overview[1]


def _empty_picture(buf, m: dict) -> None:
    from fleetmap.pictures import _plt

    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ax.text(0.5, 0.5, f"no robot placed yet ({len(m['robots'])} robots known)", ha="center")
    ax.set_axis_off()
    fig.savefig(buf, format="png")
    plt.close(fig)
