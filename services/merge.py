"""`fleetmap merge`: the main job, from N robot folders to one global map.

Extract and ingest every robot's keyframes into the place database, ask it for the
verified overlaps of every robot pair, align each overlapping pair with the aligner, then
place every robot in the reference robot's frame through the most trustworthy chain of
pairwise fits (a maximum spanning tree of the overlap graph weighted by inliers). A robot
with no trustworthy link is listed as unmerged, never placed on a guess.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from shared.client import AlignerClient, PlaceDBClient
from shared.dataset import Recording
from shared.extract import FrameExtractor, keyframe_indices
from shared.geometry import pose_to_tum
from shared.pairs import load_view, select_views

log = logging.getLogger(__name__)


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
) -> dict:
    """The whole job; writes OUT/report.json, merged.ply, trajectories/, overview.png."""
    out.mkdir(parents=True, exist_ok=True)
    timing = {"extract": 0.0, "ingest": 0.0, "overlaps": 0.0, "align": 0.0}
    t_all = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if place_db is None:
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fleetmap-")))
            place_db = stack.enter_context(embedded_service("place-db", tmp))
        if aligner is None:
            aligner = stack.enter_context(embedded_service("aligner"))
        db = stack.enter_context(PlaceDBClient(place_db, token=token))
        al = stack.enter_context(AlignerClient(aligner, timeout=900, token=token))
        from services.cli import _checked_vocabulary

        vocab = _checked_vocabulary(db, vocab_path)
        extractor = FrameExtractor(vocab)
        kf_index = {}
        for rec in recs:
            idx = keyframe_indices(rec, policy)
            kf_index[rec.robot_id] = idx
            for i in tqdm(idx, desc=f"ingest {rec.robot_id}", unit="kf", disable=quiet):
                t = time.perf_counter()
                view = load_view(rec, i)
                frame = extractor(
                    rec.robot_id, view.stamp, view.rgb, view.depth, view.intrinsics, view.T_map_cam
                )
                t2 = time.perf_counter()
                db.add_keyframe(frame)
                timing["extract"] += t2 - t
                timing["ingest"] += time.perf_counter() - t2
        t = time.perf_counter()
        overlaps, by_pair = [], {}
        for i, ra in enumerate(recs):
            for rb in recs[i + 1 :]:
                pairs = db.overlaps(ra.robot_id, rb.robot_id, wait=600)
                by_pair[(ra.robot_id, rb.robot_id)] = pairs
                overlaps += [
                    {
                        "robot_a": p["robot_a"],
                        "stamp_a": p["stamp_a"],
                        "robot_b": p["robot_b"],
                        "stamp_b": p["stamp_b"],
                        "inliers": p["inliers"],
                        "source": p["source"],
                    }
                    for p in pairs
                    if p["source"] == "cascade"  # link pairs are listed after aligning
                ]
        timing["overlaps"] = time.perf_counter() - t
        t = time.perf_counter()
        edges, fits = {}, []
        recs_by_id = {r.robot_id: r for r in recs}
        for (a, b), pairs in tqdm(by_pair.items(), desc="align", unit="pair", disable=quiet):
            ia, ib = select_views(
                pairs, recs_by_id[a], recs_by_id[b], kf_index[a], kf_index[b], max_views
            )
            if not ia:
                continue
            va = [load_view(recs_by_id[a], i) for i in ia]
            vb = [load_view(recs_by_id[b], j) for j in ib]
            views = [(x, y) for x in va for y in vb]
            res = al.align(views)
            fits.append(
                {
                    "robot_a": a,
                    "robot_b": b,
                    "views": [len(va), len(vb)],
                    **{k: v for k, v in res.items() if k != "hypotheses"},
                }
            )
            if res["merged"]:
                edges[(a, b)] = {"T_a_b": np.array(res["transform"]), "inliers": res["inliers"]}
                # the place database records the keyframe pairs co-visible under it
                fits[-1]["link_overlaps"] = db.put_link(a, b, res["transform"])
        for a, b in edges:
            overlaps += [
                {k: p[k] for k in ("robot_a", "stamp_a", "robot_b", "stamp_b", "inliers", "source")}
                for p in db.overlaps(a, b, source="link")
            ]
        timing["align"] = time.perf_counter() - t
    ids = [r.robot_id for r in recs]
    placed, chain = spanning_placement(ids, edges)
    placed, optimised = optimise_poses(placed, edges, ids[0], chain)
    report = {
        "reference": ids[0],
        "robots": {
            r.robot_id: {
                "keyframes": len(kf_index[r.robot_id]),
                "frames": len(r),
                "chain": chain.get(r.robot_id),
            }
            for r in recs
        },
        "transforms": {r: placed[r].tolist() for r in ids if r in placed},
        "overlaps": overlaps,
        "fits": fits,
        "unmerged": [r for r in ids if r not in placed],
        "pose_graph": {"edges": len(edges), "optimised": optimised},
    }
    _write_outputs(out, recs, kf_index, placed, report, voxel)
    timing["total"] = time.perf_counter() - t_all
    report["timing_s"] = {k: round(v, 3) for k, v in timing.items()}
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def _write_outputs(out: Path, recs, kf_index, placed, report, voxel: float) -> None:
    from shared.align import ROBOT_COLOURS
    from shared.geometry import apply
    from shared.mapcloud import views_cloud, write_ply

    pts, cols, names, colours = [], [], [], []
    (out / "trajectories").mkdir(exist_ok=True)
    tracks, positions, downs = {}, {}, []
    for k, rec in enumerate(recs):
        if rec.robot_id not in placed:
            continue
        T = placed[rec.robot_id]
        views = [load_view(rec, i) for i in kf_index[rec.robot_id]]
        cloud = views_cloud(views, voxel=voxel, with_color=False)
        p = apply(T, np.asarray(cloud.points))
        colour = ROBOT_COLOURS[k % len(ROBOT_COLOURS)]
        pts.append(p)
        cols.append(np.tile(colour, (len(p), 1)))
        names.append(rec.robot_id)
        colours.append(colour)
        poses = [T @ v.T_map_cam for v in views]
        tracks[rec.robot_id] = np.array([P[:3, 3] for P in poses])
        downs.extend(P[:3, 1] for P in poses)  # each camera's image-down axis
        positions[rec.robot_id] = {
            round(v.stamp, 6): P[:3, 3] for v, P in zip(views, poses, strict=True)
        }
        lines = [f"# timestamp tx ty tz qx qy qz qw (global frame = {report['reference']}'s map)"]
        lines += [
            f"{v.stamp:.6f} " + " ".join(f"{x:.6f}" for x in pose_to_tum(P))
            for v, P in zip(views, poses, strict=True)
        ]
        (out / "trajectories" / f"{rec.robot_id}.txt").write_text("\n".join(lines) + "\n")
    if pts:
        write_ply(out / "merged.ply", np.concatenate(pts), np.concatenate(cols))
        links = []
        for o in report["overlaps"]:
            if o.get("source", "cascade") != "cascade":
                continue
            pa = positions.get(o["robot_a"], {}).get(round(o["stamp_a"], 6))
            pb = positions.get(o["robot_b"], {}).get(round(o["stamp_b"], 6))
            if pa is not None and pb is not None:
                links.append((pa, pb))
        _overview(out / "overview.png", pts, tracks, names, colours, links, report, downs)
    _overlap_matrix(out / "overlap_matrix.png", [r.robot_id for r in recs], report)


def _n_cascade(report) -> int:
    return sum(o.get("source", "cascade") == "cascade" for o in report["overlaps"])


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _top_down_basis(points: np.ndarray, downs) -> np.ndarray:
    """Two axes (3, 2) spanning the floor plane. Gravity: the mean image-down axis of the
    cameras, when they agree (upright cameras on robots or in hands); otherwise the
    points' axis of least spread."""
    c = points - points.mean(0)
    down = np.mean(downs, axis=0) if len(downs) else np.zeros(3)
    if np.linalg.norm(down) > 0.5:
        g = down / np.linalg.norm(down)
        flat = c - np.outer(c @ g, g)
        _, V = np.linalg.eigh(np.cov(flat.T))
        u = V[:, 2]
        return np.stack([u, np.cross(g, u)], axis=1)
    _, V = np.linalg.eigh(np.cov(c.T))
    return V[:, [2, 1]]


def _overview(path: Path, pts, tracks, names, colours, links, report, downs=()) -> None:
    """Top-down picture: map points per robot, trajectories, overlap links (grey)."""
    plt = _plt()
    allp = np.concatenate(pts)
    c = allp.mean(0)
    basis = _top_down_basis(allp, downs)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    for p, name, colour in zip(pts, names, colours, strict=True):
        uv = (p[:: max(1, len(p) // 20000)] - c) @ basis
        ax.scatter(uv[:, 0], uv[:, 1], s=0.3, color=colour, alpha=0.4)
        tr = (tracks[name] - c) @ basis
        ax.plot(tr[:, 0], tr[:, 1], "-o", ms=2, color=colour * 0.7, label=name)
    for pa, pb in links:
        uv = (np.stack([pa, pb]) - c) @ basis
        ax.plot(uv[:, 0], uv[:, 1], "-", color="0.3", lw=0.6, alpha=0.6)
    ax.set_aspect("equal")
    ax.legend(loc="best")
    ax.set_title(
        f"fleetmap: {len(names)} robots merged, {len(report['unmerged'])} unmerged, "
        f"{_n_cascade(report)} verified overlaps (grey), reference "
        f"{report['reference']}"
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _overlap_matrix(path: Path, names: list[str], report) -> None:
    """Verified keyframe pairs between every two robots, as a matrix (thesis Fig. 1.1)."""
    plt = _plt()
    k = {n: i for i, n in enumerate(names)}
    M = np.zeros((len(names), len(names)), int)
    for o in report["overlaps"]:
        i, j = k[o["robot_a"]], k[o["robot_b"]]
        M[i, j] += 1
        M[j, i] += 1
    fig, ax = plt.subplots(figsize=(1.2 + 0.6 * len(names), 1 + 0.6 * len(names)), dpi=110)
    ax.imshow(M, cmap="Blues")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(
                j,
                i,
                str(M[i, j]),
                ha="center",
                va="center",
                color="white" if M[i, j] > M.max() / 2 else "black",
            )
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_title("verified pairs")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
