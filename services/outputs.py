"""What `fleetmap merge` (and `fleetmap map`) write: merged.ply (and .pcd), every frame's
trajectory in the reference frame (TUM), the robots' pose graph (g2o) and the pictures
(overview.png, overlap_matrix.png); report.json's content is `fleetmap.fleet.report`'s."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from fleetmap import pictures
from fleetmap.dataset import Recording
from fleetmap.errors import BadInput
from fleetmap.fleet.types import MergeParams
from fleetmap.geometry import apply, pose_to_tum
from fleetmap.mapcloud import ROBOT_COLOURS, write_pcd, write_ply

log = logging.getLogger(__name__)


#: The files `merge` and `map` write in their --out folder, beside `trajectories/`
OUTPUT_FILES = (
    "report.json", "merged.ply", "merged.pcd", "overview.png", "overlap_matrix.png",
    "pose_graph.g2o", "fleet.mcap",
)  # fmt: skip


def prepare_out(out: Path, robots=()) -> PreviousRun:
    """--out checked before any work: a folder or nothing yet, where no file this writes is
    a folder (`robots`: the trajectories' names) and `trajectories` is not a file (a
    `report.json` folder failed the run at its end, the other files written), made and
    written to once (a read-only --out failed after the whole merge). Returns what a
    previous run wrote there that this run may not write again, to remove once it has
    written its own (`PreviousRun`)."""
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out} exists and is not a folder")
    tracks = out / "trajectories"
    names = [*OUTPUT_FILES, *(f"trajectories/{r}.txt" for r in robots)]
    for name in names:
        if (out / name).is_dir():
            raise BadInput(f"--out {out}: {name} is a folder, where this writes a file")
    if tracks.exists() and not tracks.is_dir():
        raise BadInput(f"--out {out}: trajectories is a file, where this writes a folder")
    previous = PreviousRun.of(out)
    for folder in (out, tracks):  # made, and written to once
        _writable(folder, ".fleetmap-probe", f"--out {folder}")
    return previous


@dataclasses.dataclass(frozen=True)
class PreviousRun:
    """The files a previous `merge` or `map` wrote in --out that a new run may not write
    again (trajectories/R.txt of a robot it does not place, merged.pcd without --pcd), by
    what its report.json names (robots, --pcd), each with its state (inode, mtime, size)
    then. Removed after the new run has written its outputs (`remove_unwritten`) where
    still as they were: a reader of trajectories/ took a robot of the last run for this
    fleet's. Nothing else is touched: an outside tester's own trajectories/notes.txt and
    merged.pcd went with a merge that then failed to reach its aligner."""

    files: dict  # Path -> (st_ino, st_mtime_ns, st_size)

    @classmethod
    def of(cls, out: Path) -> PreviousRun:
        try:
            report = json.loads((out / "report.json").read_text())
            robots, pcd = report["robots"], report.get("parameters", {}).get("pcd") is True
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            robots = None
        if not isinstance(robots, dict | list):  # no run of ours there, or none we can read
            return cls({})
        names = [Path("trajectories") / f"{r}.txt" for r in robots if _plain(r)]
        paths = [out / n for n in names + [Path("merged.pcd")] * pcd]
        return cls({f: _state(f) for f in paths if f.is_file()})

    def remove_unwritten(self) -> None:
        """Remove the previous run's files this run has not written again."""
        stale = [f for f, st in self.files.items() if f.is_file() and _state(f) == st]
        for f in stale:
            f.unlink()
        if stale:
            log.info("%d outputs of a previous run removed: %s", len(stale), stale)


def _plain(name) -> bool:
    """A robot id that names a file in trajectories/ and nothing beyond it."""
    return isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name


def _state(f: Path) -> tuple[int, int, int]:
    st = f.stat()
    return st.st_ino, st.st_mtime_ns, st.st_size


def merge_summary(report: dict, ids: list[str], out: Path) -> str:
    """What `fleetmap merge` prints when done: how many robots it merged, why each other
    one is not (the report's reason, not "no trustworthy overlap" beside 30 verified
    overlaps), where the results are and how to look at them."""
    n = pictures.n_cascade(report)
    merged = [r for r in ids if r not in report["unmerged"]]
    lines = [
        f"merged {len(merged)} of {len(ids)} robots into {report['reference']}'s frame ({n} "
        f"verified overlaps, {len(report['overlaps']) - n} more co-visible once aligned, "
        f"{report['timing_s']['total']:.1f} s)"
    ]
    for r, why in report["unmerged_reasons"].items():
        why = why if len(why) <= 300 else f"{why[:300]}... (report.json: unmerged_reasons)"
        lines.append(f"unmerged {r}: {why}")
    lines += [
        f"results: {out / 'report.json'}, {out / 'merged.ply'}, {out / 'overview.png'}",
        f"look at: {out / 'overview.png'} (the map from above); {out / 'fleet.mcap'} in "
        "Foxglove (docs/OPERATIONS.md); the map in 3D while robots stream: `fleetmap serve` "
        "and `fleetmap stream`, then http://127.0.0.1:8100/ (README, 'The live map')",
    ]
    return "\n".join(lines)


def prepare_file(path: Path, flag: str = "-o") -> None:
    """An output file's place checked before the work that makes it (`vocab train` trained
    for minutes, then failed on a missing or read-only folder): its folder made where
    missing and written to once, the name not a folder."""
    if path.is_dir():
        raise BadInput(f"{flag} {path} is a folder, where this writes a file")
    _writable(path.parent, f".{path.name}.probe", f"{flag} {path}")


def _writable(folder: Path, probe: str, named: str) -> None:
    """`folder` made where missing and a file `probe` written there once; BadInput naming
    `named` where it cannot be."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / probe).write_bytes(b"")
        (folder / probe).unlink()
    except OSError as exc:
        raise BadInput(f"{named}: cannot write there ({exc.strerror})") from None


def prepare_empty(out: Path) -> None:
    """A folder this fills whole (`simulate`): new or empty, so that nothing of an earlier
    run stays beside this one's (robot1 of a two-robot run beside a one-robot run's
    T_true.json)."""
    if out.exists() and not out.is_dir():
        raise BadInput(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise BadInput(f"{out} is not empty: give a new or empty folder")


@dataclasses.dataclass
class Drawing:
    """What the pictures need from the placed maps (all in the reference frame)."""

    points: list = dataclasses.field(default_factory=list)  # per merged robot, (N, 3)
    names: list = dataclasses.field(default_factory=list)
    colours: list = dataclasses.field(default_factory=list)
    tracks: dict = dataclasses.field(default_factory=dict)  # robot -> keyframe positions
    positions: dict = dataclasses.field(default_factory=dict)  # robot -> {stamp: position}
    downs: list = dataclasses.field(default_factory=list)  # cameras' image-down axes


def write_maps(
    out: Path, recs, kf_index, clouds, placed, edges, params: MergeParams, fleet=None
) -> Drawing:
    """merged.ply (image colour, per-point robot index; `params.voxel_m`, and merged.pcd with
    `params.pcd`), trajectories of every frame and pose_graph.g2o; returns what the pictures
    need. `placed`: T_ref_r per placed robot; `edges`: the fits placed on. With `fleet`
    (`fleetmap.fleet.correct.FleetCorrection`), a drift-corrected robot's cloud and poses
    are its corrected ones and pose_graph.g2o is the keyframe graph."""
    (out / "trajectories").mkdir(exist_ok=True)
    d, cols, robot_idx = Drawing(), [], []
    ref = recs[0].robot_id
    for k, rec in enumerate(recs):
        rid = rec.robot_id
        if rid not in placed:
            continue
        T_ref_r = placed[rid] if fleet is None else fleet.rigid(rid, placed[rid])
        pose = _frame_poses(rid, T_ref_r, fleet)
        corrected = fleet is not None and rid in fleet.robots and fleet.robots[rid].applied
        p, c = (fleet.cloud(rid) if corrected else clouds[rid]).voxelised(params.voxel_m)
        d.points.append(p if corrected else apply(T_ref_r, p))
        cols.append(c)
        robot_idx.append(np.full(len(p), k, np.uint16))
        d.names.append(rid)
        d.colours.append(ROBOT_COLOURS[k % len(ROBOT_COLOURS)])
        kfs = [rec.frames[i] for i in kf_index[rid]]
        poses = [pose(f) for f in kfs]
        d.tracks[rid] = np.array([P[:3, 3] for P in poses])
        d.downs.extend(P[:3, 1] for P in poses)
        d.positions[rid] = {round(f.stamp, 6): P[:3, 3] for f, P in zip(kfs, poses, strict=True)}
        _write_trajectory(out / "trajectories" / f"{rid}.txt", rec, pose, ref)
    if d.points:
        pts, col, idx = np.concatenate(d.points), np.concatenate(cols), np.concatenate(robot_idx)
        write_ply(out / "merged.ply", pts, col, robot=idx)
        if params.pcd:
            write_pcd(out / "merged.pcd", pts, col, idx)
    if fleet is not None and any(c.applied for c in fleet.robots.values()):
        fleet.solution.write_g2o(out / "pose_graph.g2o")  # the keyframe graph
    else:
        write_g2o(out / "pose_graph.g2o", [r.robot_id for r in recs], placed, edges)
    return d


def _frame_poses(rid: str, T_ref_map: np.ndarray, fleet):
    """A frame's camera pose in the reference frame: drift-corrected, or rigidly placed."""
    corr = fleet.robots.get(rid) if fleet is not None else None
    if corr is not None and corr.applied:
        return lambda f: corr.frame_pose(f.stamp, f.T_map_cam)
    return lambda f: T_ref_map @ f.T_map_cam


def write_pictures(out: Path, ids: list[str], d: Drawing, report: dict) -> None:
    """overview.png (top-down, verified overlaps drawn) and overlap_matrix.png."""
    if d.points:
        links = []
        for o in report["overlaps"]:
            if o.get("source", "cascade") != "cascade":
                continue
            pa = d.positions.get(o["robot_a"], {}).get(round(o["stamp_a"], 6))
            pb = d.positions.get(o["robot_b"], {}).get(round(o["stamp_b"], 6))
            if pa is not None and pb is not None:
                links.append((pa, pb))
        pictures.overview(
            out / "overview.png", d.points, d.tracks, d.names, d.colours, links, report, d.downs
        )
    pictures.overlap_matrix(out / "overlap_matrix.png", ids, report)


def _write_trajectory(path: Path, rec: Recording, pose, ref: str) -> None:
    """Every frame's camera pose in the global frame (`pose(frame)`), TUM format."""
    rows = [[f.stamp, *pose_to_tum(pose(f))] for f in rec.frames if f.T_map_cam is not None]
    write_tum(path, rows, ref)


def write_tum(path: Path, rows, ref: str) -> None:
    """A trajectory file in TUM format: rows [stamp, tx, ty, tz, qx, qy, qz, qw], the
    camera in `ref`'s map frame."""
    lines = [f"# timestamp tx ty tz qx qy qz qw (camera to {ref}'s map frame)"]
    lines += [f"{row[0]:.6f} " + " ".join(f"{x:.6f}" for x in row[1:]) for row in rows]
    path.write_text("\n".join(lines) + "\n")


def write_g2o(path: Path, ids: list[str], placed: dict, edges: dict) -> None:
    """The robots' pose graph in g2o's SE3 format: one vertex per placed robot (its map
    frame in the reference's), one edge per gated pairwise fit, information scaled by the
    fit's inliers. The reference's vertex is fixed (where there is one: a live map of no
    robot, or none placed, is a graph of no vertex; `FIX 0` of no vertex 0 and an
    IndexError on no robot before: an outside tester's review)."""
    idx = {r: k for k, r in enumerate(ids)}
    named = ", ".join(f"{idx[r]} {r}" for r in ids if r in placed)
    unplaced = [r for r in ids if r not in placed]  # listed as vertices before: none are
    lines = [f"# fleetmap pose graph: vertex robot: {named or 'none'}"]
    lines += [f"# not placed (no vertex): {', '.join(unplaced)}"] * bool(unplaced)
    for r in ids:
        if r in placed:
            lines.append(f"VERTEX_SE3:QUAT {idx[r]} " + _g2o_pose(placed[r]))
    if ids and ids[0] in placed:  # none placed (an empty or unaligned live map): no vertex
        lines.append(f"FIX {idx[ids[0]]}")
    for (a, b), e in edges.items():
        info = _g2o_information(np.eye(6) * max(float(e["inliers"]), 1.0))
        upper = " ".join(f"{info[i, j]:g}" for i in range(6) for j in range(i, 6))
        lines.append(f"EDGE_SE3:QUAT {idx[a]} {idx[b]} {_g2o_pose(e['T_a_b'])} {upper}")
    path.write_text("\n".join(lines) + "\n")


def _g2o_information(info: np.ndarray) -> np.ndarray:
    """Open3D's (rotation, translation) information to g2o's (translation, quaternion
    vector): blocks swapped, rotation scaled for the half angle (dtheta = 2 dq)."""
    J = np.zeros((6, 6))
    J[0:3, 3:6] = 2.0 * np.eye(3)  # rotation <- quaternion vector
    J[3:6, 0:3] = np.eye(3)  # translation <- translation
    return J.T @ info @ J


def _g2o_pose(T: np.ndarray) -> str:
    return " ".join(f"{x:.9f}" for x in pose_to_tum(T))
