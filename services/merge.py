"""`fleetmap merge`: the main job, from N robot folders to one global map.

Extract and ingest every robot's keyframes into the place database, ask it for the
verified overlaps of every robot pair, align each overlapping pair with the aligner, then
place every robot in the reference robot's frame through the most trustworthy chain of
pairwise fits (a maximum spanning tree of the overlap graph weighted by inliers). A robot
with no trustworthy link is listed as unmerged, never placed on a guess.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import logging
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from shared import pictures
from shared.client import AlignerClient, PlaceDBClient
from shared.dataset import Recording
from shared.errors import Unavailable
from shared.extract import keyframe_indices
from shared.extract_pool import extract_keyframes
from shared.geometry import apply, pose_to_tum
from shared.mapcloud import ROBOT_COLOURS, MapCloud, write_pcd, write_ply
from shared.pairs import load_view, select_views

log = logging.getLogger(__name__)

#: report.json layout version (2: schema_version, transform_convention, parameters).
REPORT_VERSION = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def embedded_service(kind: str, data_dir: Path | None = None):
    """A service on a free loopback port in a background thread; yields its URL."""
    import uvicorn

    if kind == "place-db":
        from services.place_db.config import Settings
        from services.place_db.main import create_app

        app = create_app(Settings(data_dir=data_dir) if data_dir else Settings())
    else:
        from services.aligner.main import create_app as create_aligner

        app = create_aligner()
    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, name=f"embedded-{kind}", daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{port}"
    client = PlaceDBClient(url)
    try:
        client.wait_ready(60)
        yield url
    finally:
        client.close()
        server.should_exit = True
        thread.join(30)


@contextlib.contextmanager
def embedded_process(kind: str, data_dir: Path | None = None):
    """A service as a child process on a free loopback port; yields its URL. The place
    database runs so: its overlap worker then has a core (and an interpreter lock) of its
    own while this process posts keyframes."""
    port = _free_port()
    cmd = [sys.executable, "-m", "services.cli", "serve", kind, "--port", str(port)]
    if data_dir is not None:
        cmd += ["--data-dir", str(data_dir)]
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryFile() as errors:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errors)
        client = PlaceDBClient(url)
        try:
            try:
                client.wait_ready(60, alive=lambda: proc.poll() is None, poll_s=0.05)
            except Unavailable:
                if proc.poll() is None:
                    raise
                errors.seek(0)
                tail = errors.read().decode(errors="replace").strip().splitlines()[-1:]
                raise Unavailable(f"embedded {kind} exited ({proc.returncode}): {tail}") from None
            yield url
        finally:
            client.close()
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def spanning_placement(
    robots: list[str], edges: dict[tuple[str, str], dict]
) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """T_ref_robot for every robot reachable from robots[0] through merged edges, choosing
    the strongest links first (Prim's maximum spanning tree on inliers).

    edges[(a, b)] holds {"T_a_b": 4x4, "inliers": int}; returns transforms and the chain
    of robots each placement went through."""
    ref = robots[0]
    placed = {ref: np.eye(4)}
    chain = {ref: [ref]}
    while True:
        best = None
        for (a, b), e in edges.items():
            for src, dst, T in ((a, b, e["T_a_b"]), (b, a, np.linalg.inv(e["T_a_b"]))):
                if src in placed and dst not in placed and (best is None or e["inliers"] > best[0]):
                    best = (e["inliers"], src, dst, T)
        if best is None:
            return placed, chain
        _, src, dst, T = best
        placed[dst] = placed[src] @ T
        chain[dst] = chain[src] + [dst]


def optimise_poses(
    placed: dict[str, np.ndarray],
    edges: dict[tuple[str, str], dict],
    reference: str,
    chain: dict[str, list[str]] | None = None,
) -> tuple[dict[str, np.ndarray], bool]:
    """Pose-graph optimisation (Open3D) when the merged edges form cycles; the spanning
    tree's placement is the initial guess and the reference robot stays fixed."""
    import open3d as o3d

    names = [n for n in placed]
    used = [(a, b, e) for (a, b), e in edges.items() if a in placed and b in placed]
    if len(used) <= len(names) - 1:
        return placed, False  # a tree: nothing to reconcile
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    order = [reference] + [n for n in names if n != reference]
    idx = {n: k for k, n in enumerate(order)}
    for n in order:
        graph.nodes.append(reg.PoseGraphNode(placed[n]))
    # spanning-tree links are the certain backbone; the links closing cycles may be pruned
    tree = {frozenset(c[-2:]) for c in (chain or {}).values() if len(c) >= 2}
    for a, b, e in used:  # edge: source b, target a, T_a_b maps b's frame into a's
        # weighed by inliers: each fit's Open3D information matrix was tried (issue 10) and
        # placed the 8-robot simulated fleet worse (0.40 against 0.14 cm at worst)
        info = np.eye(6) * max(float(e["inliers"]), 1.0)
        graph.edges.append(
            reg.PoseGraphEdge(
                idx[b], idx[a], e["T_a_b"], info, uncertain=frozenset((a, b)) not in tree
            )
        )
    reg.global_optimization(
        graph,
        reg.GlobalOptimizationLevenbergMarquardt(),
        reg.GlobalOptimizationConvergenceCriteria(),
        reg.GlobalOptimizationOption(
            max_correspondence_distance=0.05, edge_prune_threshold=0.25, reference_node=0
        ),
    )
    T_ref = np.linalg.inv(np.asarray(graph.nodes[0].pose))
    return {n: T_ref @ np.asarray(graph.nodes[idx[n]].pose) for n in order}, True


def run_merge(
    recs: list[Recording],
    out: Path,
    policy,
    vocab_path=None,
    place_db: str | None = None,
    aligner: str | None = None,
    max_views: int = 12,
    voxel: float = 0.03,
    quiet: bool = False,
    token: str | None = None,
    workers: int | None = None,
    pcd: bool = False,
) -> dict:
    """The whole job; writes OUT/report.json, merged.ply, pose_graph.g2o, trajectories/,
    overview.png and overlap_matrix.png. Stages: extract (every core) while the services
    start, ingest, overlaps, align, place (spanning tree, pose graph), write; the place
    database registers the links meanwhile."""
    _check_reachable(place_db, aligner, token)  # before any long work
    out.mkdir(parents=True, exist_ok=True)
    timing = {"extract": 0.0, "ingest": 0.0, "overlaps": 0.0, "align": 0.0, "outputs": 0.0}
    t_all = time.perf_counter()
    kf_index = {r.robot_id: keyframe_indices(r, policy) for r in recs}
    ids = [r.robot_id for r in recs]
    with contextlib.ExitStack() as stack:
        # the workers extract while the services start
        keyframes = extract_keyframes(recs, kf_index, vocab_path, workers)
        stack.callback(keyframes.close)
        t = time.perf_counter()
        place_db, aligner = _services(stack, place_db, aligner)
        timing["start"] = time.perf_counter() - t
        db = stack.enter_context(PlaceDBClient(place_db, token=token))
        al = stack.enter_context(AlignerClient(aligner, timeout=900, token=token))
        from services.cli import _checked_vocabulary

        _checked_vocabulary(db, vocab_path)
        clouds = ingest(keyframes, db, sum(map(len, kf_index.values())), timing, quiet)
        t = time.perf_counter()
        overlaps, by_pair = find_overlaps(db, ids)
        timing["overlaps"] = time.perf_counter() - t
        t = time.perf_counter()
        edges, fits, links = align_pairs(db, al, recs, kf_index, by_pair, max_views, quiet)
        timing["align"] = time.perf_counter() - t
        # placed and written while the place database registers the links
        t = time.perf_counter()
        placed, chain = spanning_placement(ids, edges)
        placed, optimised = optimise_poses(placed, edges, ids[0], chain)
        drawing = write_maps(out, recs, kf_index, clouds, placed, edges, voxel, pcd)
        timing["outputs"] = time.perf_counter() - t
        t = time.perf_counter()
        for k, future in links.items():
            fits[k]["link_overlaps"] = future.result()
        for a, b in edges:
            overlaps += [
                {k: p[k] for k in ("robot_a", "stamp_a", "robot_b", "stamp_b", "inliers", "source")}
                for p in db.overlaps(a, b, source="link")
            ]
        timing["links"] = time.perf_counter() - t
    report = {
        "schema_version": REPORT_VERSION,
        "reference": ids[0],
        "transform_convention": (
            "transforms[R] is T_ref_R: it maps points of robot R's map frame into the "
            "reference robot's map frame (row-major 4x4, metres)"
        ),
        "robots": {
            r.robot_id: {
                "keyframes": len(kf_index[r.robot_id]),
                "frames": len(r),
                "source": str(r.root),
                "chain": chain.get(r.robot_id),
            }
            for r in recs
        },
        "transforms": {r: placed[r].tolist() for r in ids if r in placed},
        "overlaps": overlaps,
        "fits": fits,
        "unmerged": [r for r in ids if r not in placed],
        "pose_graph": {"edges": len(edges), "optimised": optimised},
        "parameters": {
            "keyframes": dataclasses.asdict(policy) if dataclasses.is_dataclass(policy) else None,
            "max_views": max_views,
            "voxel_m": voxel,
            "pcd": pcd,
            "vocabulary": str(vocab_path) if vocab_path else "default",
        },
    }
    t = time.perf_counter()
    write_pictures(out, ids, drawing, report)
    timing["outputs"] += time.perf_counter() - t
    timing["total"] = time.perf_counter() - t_all
    report["timing_s"] = {k: round(v, 3) for k, v in timing.items()}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def _check_reachable(place_db: str | None, aligner: str | None, token: str | None) -> None:
    """Given service URLs answer /healthz (one try, a few seconds), or Unavailable."""
    for url, client in ((place_db, PlaceDBClient), (aligner, AlignerClient)):
        if url is not None:
            with client(url, timeout=10, token=token) as c:
                c.health()


def _services(stack: contextlib.ExitStack, place_db: str | None, aligner: str | None):
    """The given service URLs, or both services embedded on free loopback ports."""
    if place_db is None:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fleetmap-")))
        place_db = stack.enter_context(embedded_process("place-db", tmp))
    if aligner is None:
        aligner = stack.enter_context(embedded_service("aligner"))
        # Open3D and the MLP's torch (1.6 s to import) load while the robots are ingested
        threading.Thread(target=_warm_up, args=("open3d", "torch"), daemon=True).start()
    return place_db, aligner


def _warm_up(*modules: str) -> None:
    for name in modules:
        importlib.import_module(name)


def ingest(
    keyframes, db, total: int, timing: dict, quiet: bool, in_flight: int = 8
) -> dict[str, MapCloud]:
    """POST every extracted keyframe, up to `in_flight` at once (the place database commits
    concurrent keyframes together); returns each robot's map cloud (all keyframes).

    timing["extract"]: time spent waiting for the extraction workers; timing["ingest"]:
    from the last keyframe extracted to the last one acknowledged."""
    parts: dict[str, list] = {}
    bar = tqdm(total=total, desc="extract+ingest", unit="kf", disable=quiet)
    pending: deque = deque()
    with ThreadPoolExecutor(4) as posters:
        t = time.perf_counter()
        for kf in keyframes:
            timing["extract"] += time.perf_counter() - t
            pending.append(posters.submit(db.add_keyframe, kf.frame))
            parts.setdefault(kf.robot_id, []).append(kf)
            while len(pending) > in_flight or (pending and pending[0].done()):
                pending.popleft().result()  # raises the first failure
                bar.update()
            t = time.perf_counter()
        t = time.perf_counter()
        while pending:
            pending.popleft().result()
            bar.update()
        timing["ingest"] = time.perf_counter() - t
    bar.close()
    return {r: MapCloud.from_keyframes(kfs) for r, kfs in parts.items()}


def find_overlaps(db, ids: list[str]) -> tuple[list[dict], dict]:
    """Verified keyframe pairs of every robot pair (the report's cascade overlaps)."""
    overlaps, by_pair = [], {}
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            pairs = db.overlaps(a, b, wait=600)
            by_pair[(a, b)] = pairs
            overlaps += [
                {k: p[k] for k in ("robot_a", "stamp_a", "robot_b", "stamp_b", "inliers", "source")}
                for p in pairs
                if p["source"] == "cascade"  # link pairs are listed after aligning
            ]
    return overlaps, by_pair


def align_pairs(db, al, recs, kf_index, by_pair, max_views: int, quiet: bool, workers: int = 2):
    """Send each overlapping pair's views near its overlaps to the aligner (two pairs at a
    time); register each gated alignment with the place database, in the background.
    Returns (edges, fits, links: fit index -> future of the link overlaps recorded)."""
    recs_by_id = {r.robot_id: r for r in recs}

    def one(item):
        (a, b), pairs = item
        ia, ib = select_views(
            pairs, recs_by_id[a], recs_by_id[b], kf_index[a], kf_index[b], max_views
        )
        if not ia:
            return None
        va = [load_view(recs_by_id[a], i) for i in ia]
        vb = [load_view(recs_by_id[b], j) for j in ib]
        res = al.align([(x, y) for x in va for y in vb])
        fit = {"robot_a": a, "robot_b": b, "views": [len(va), len(vb)]}
        return fit | {k: v for k, v in res.items() if k != "hypotheses"}

    edges, fits, links = {}, [], {}
    linker = ThreadPoolExecutor(1)
    with (
        ThreadPoolExecutor(workers) as pool,
        tqdm(total=len(by_pair), desc="align", unit="pair", disable=quiet) as bar,
    ):
        for fit in pool.map(one, by_pair.items()):
            bar.update()
            if fit is None:
                continue
            fits.append(fit)
            if fit["merged"]:
                a, b = fit["robot_a"], fit["robot_b"]
                edges[(a, b)] = {"T_a_b": np.array(fit["transform"]), "inliers": fit["inliers"]}
                # the place database records the keyframe pairs co-visible under it
                links[len(fits) - 1] = linker.submit(db.put_link, a, b, fit["transform"])
    linker.shutdown(wait=False)  # the submitted links still run
    return edges, fits, links


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
    out: Path, recs, kf_index, clouds, placed, edges, voxel: float = 0.03, pcd: bool = False
) -> Drawing:
    """merged.ply (image colour, per-point robot index), trajectories of every frame and
    pose_graph.g2o; returns what the pictures need."""
    (out / "trajectories").mkdir(exist_ok=True)
    d, cols, robot_idx = Drawing(), [], []
    ref = recs[0].robot_id
    for k, rec in enumerate(recs):
        rid = rec.robot_id
        if rid not in placed:
            continue
        T = placed[rid]
        p, c = clouds[rid].voxelised(voxel)
        d.points.append(apply(T, p))
        cols.append(c)
        robot_idx.append(np.full(len(p), k, np.uint16))
        d.names.append(rid)
        d.colours.append(ROBOT_COLOURS[k % len(ROBOT_COLOURS)])
        kfs = [rec.frames[i] for i in kf_index[rid]]
        poses = [T @ f.T_map_cam for f in kfs]
        d.tracks[rid] = np.array([P[:3, 3] for P in poses])
        d.downs.extend(P[:3, 1] for P in poses)
        d.positions[rid] = {round(f.stamp, 6): P[:3, 3] for f, P in zip(kfs, poses, strict=True)}
        _write_trajectory(out / "trajectories" / f"{rid}.txt", rec, T, ref)
    if d.points:
        pts, col, idx = np.concatenate(d.points), np.concatenate(cols), np.concatenate(robot_idx)
        write_ply(out / "merged.ply", pts, col, robot=idx)
        if pcd:
            write_pcd(out / "merged.pcd", pts, col, idx)
    write_g2o(out / "pose_graph.g2o", [r.robot_id for r in recs], placed, edges)
    return d


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


def _write_trajectory(path: Path, rec: Recording, T_ref_map: np.ndarray, ref: str) -> None:
    """Every frame's camera pose in the global frame, TUM format."""
    lines = [f"# timestamp tx ty tz qx qy qz qw (camera to {ref}'s map frame)"]
    lines += [
        f"{f.stamp:.6f} " + " ".join(f"{x:.6f}" for x in pose_to_tum(T_ref_map @ f.T_map_cam))
        for f in rec.frames
        if f.T_map_cam is not None
    ]
    path.write_text("\n".join(lines) + "\n")


def write_g2o(path: Path, ids: list[str], placed: dict, edges: dict) -> None:
    """The robots' pose graph in g2o's SE3 format: one vertex per placed robot (its map
    frame in the reference's), one edge per gated pairwise fit, information scaled by the
    fit's inliers. The reference's vertex is fixed."""
    idx = {r: k for k, r in enumerate(ids)}
    lines = [f"# fleetmap pose graph: vertex k = robot {', '.join(ids)}"]
    for r in ids:
        if r in placed:
            lines.append(f"VERTEX_SE3:QUAT {idx[r]} " + _g2o_pose(placed[r]))
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
