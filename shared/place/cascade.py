"""The retrieval cascade (thesis Algorithm 3) over an in-memory place index.

Global stage: the query's GIST goes to its m nearest coarse clusters (an IVF index,
faiss, vectors stored as float16), every keyframe in those inverted lists within GIST
distance `tr` is a candidate, the closest `max_candidates` are kept. Beside it, the inverted
file over visual words (`postings`) adds up to `ivf_candidates` keyframes that share the
query's most informative words, so a revisit whose GIST falls outside the probed clusters
is still considered; both sources go through the same local stage. Local stage: the
Bhattacharyya distance between bags of words (eq. 2.9) filters and ranks them, the best
few are matched with SIFT and, with N > 8 matches, verified by a fundamental-matrix
RANSAC. The winner is the verified candidate with most inliers, or none.

Only GIST, BoW and ids live in memory (about 3 KB per keyframe); each candidate's local
features are loaded from storage when the local stage needs them.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from fleetmap.errors import StorageCorrupt, UnknownKeyframe
from fleetmap.frame import Frame
from fleetmap.geometry import invert
from fleetmap.matching import verify_pair
from fleetmap.place.index import PlaceIndex
from fleetmap.place.types import (
    DEFAULT_CASCADE,
    Candidate,
    CascadeParams,
    CascadeResult,
    Filter,
    Stage,
)


def local_stage(
    query: Frame,
    cands: list[Candidate],
    index: PlaceIndex,
    load: Callable[[int], Frame],
    p: CascadeParams,
) -> tuple[list[Candidate], list[Stage]]:
    """BoW filter and ranking, then SIFT matching and epipolar verification."""
    t0 = time.perf_counter()
    if cands:
        d = index.bow_distances(query.bow_ids, query.bow_counts, np.array([c.kf_id for c in cands]))
        for c, di in zip(cands, d, strict=True):
            c.bow_distance = float(di)
    passed = sorted(
        (c for c in cands if c.bow_distance < p.bow_threshold), key=lambda c: c.bow_distance
    )
    chosen, per_robot = [], {}
    for c in passed:
        if per_robot.get(c.robot_code, 0) < p.max_verify_per_robot:
            per_robot[c.robot_code] = per_robot.get(c.robot_code, 0) + 1
            chosen.append(c)
        if len(chosen) >= p.max_verify:
            break
    t1 = time.perf_counter()
    matched, verified = 0, []

    for c in chosen:
        try:
            other = load(c.kf_id)
        except (StorageCorrupt, UnknownKeyframe):  # corrupted (logged, counted by the store),
            continue  # or deleted while this query ran: the other candidates stand
        c.verification = verify_pair(
            query.keypoints,
            query.descriptors,
            other.keypoints,
            other.descriptors,
            p.match,
            _points(query),
            _points(other),
        )
        matched += c.verification.matches >= p.match.min_matches
        if c.verification.verified:
            verified.append(c)
    chosen = [c for c in chosen if c.verification is not None]
    verified.sort(key=lambda c: -c.verification.inliers)
    match_ms = sum(c.verification.match_ms for c in chosen)
    ransac_ms = sum(c.verification.ransac_ms for c in chosen)
    load_ms = 1000 * (time.perf_counter() - t1) - match_ms - ransac_ms
    return verified, [
        Stage("bow", len(passed), 1000 * (t1 - t0)),
        Stage("sift_matches", matched, match_ms + load_ms),
        Stage("epipolar", len(verified), ransac_ms),
    ]


def _points(f: Frame) -> tuple[np.ndarray, np.ndarray] | None:
    return None if f.points is None else (f.points, f.point_valid)


def run_cascade(
    query: Frame,
    index: PlaceIndex,
    load: Callable[[int], Frame],
    p: CascadeParams = DEFAULT_CASCADE,
    flt: Filter | None = None,
) -> CascadeResult:
    """Algorithm 3: the winner among stored keyframes for one query frame, or none."""
    t0 = time.perf_counter()
    flt = flt or Filter()
    cands, stages = index.global_stage(query.gist, p, flt)
    extra, stage = index.word_stage(
        (query.bow_ids, query.bow_counts), query.gist, p, flt, [c.kf_id for c in cands]
    )
    cands, stages = cands + extra, [*stages, stage]
    verified, local = local_stage(query, cands, index, load, p)
    return CascadeResult(
        verified[0] if verified else None,
        verified,
        stages + local,
        len(index),
        1000 * (time.perf_counter() - t0),
    )


class CovisTarget:
    """A target keyframe's side of `sparse_covisibility`, which depends on it alone and is
    computed once per keyframe: its map-to-camera transform, the depths of its feature
    points in front of it, and a KD-tree of their pixels."""

    def __init__(self, target: Frame):
        from scipy.spatial import cKDTree

        self.K = target.intrinsics
        self.cam = invert(target.T_map_cam)
        pa = target.points[target.point_valid].astype(np.float64)
        pa = pa @ self.cam[:3, :3].T + self.cam[:3, 3]
        pa = pa[pa[:, 2] > 0.1]
        self.depth = pa[:, 2]
        self.tree = cKDTree(self.K.project(pa)) if len(pa) else None


def covis_target(target: Frame) -> CovisTarget | None:
    """The target's prepared side; None where it can see nothing (no map points, pose or
    intrinsics, or no point in front of its camera)."""
    if target.points is None or target.T_map_cam is None or target.intrinsics is None:
        return None
    t = CovisTarget(target)
    return t if t.tree is not None else None


def covis_source(source: Frame) -> np.ndarray:
    """The source's side: its valid map points, float64 (M, 3); none without depth."""
    if source.points is None:
        return np.zeros((0, 3))
    return source.points[source.point_valid].astype(np.float64)


def covisibility_many(
    target: CovisTarget | None,
    sources: list[np.ndarray],
    T_target_source: np.ndarray,
    radius_px: float = 24.0,
) -> list[tuple[int, float]]:
    """`sparse_covisibility` of one prepared target and many sources' points
    (`covis_source`), in one pass: the sources' points are mapped, projected and looked up
    in the target's KD-tree together. One (points seen, share) per source."""
    sizes = [len(s) for s in sources]
    if target is None or not sum(sizes):
        return [(0, 0.0)] * len(sources)
    M = target.cam @ T_target_source
    pb = np.concatenate(sources) @ M[:3, :3].T + M[:3, 3]
    owner = np.repeat(np.arange(len(sources)), sizes)
    z = pb[:, 2]
    front = z > 0.1
    ub = target.K.project(pb[front])
    K = target.K
    inside = (ub[:, 0] >= 0) & (ub[:, 0] < K.width) & (ub[:, 1] >= 0) & (ub[:, 1] < K.height)
    counts = np.zeros(len(sources), np.int64)
    if inside.any():
        d, k = target.tree.query(ub[inside], distance_upper_bound=radius_px)
        near = np.isfinite(d)
        za, zb = target.depth[k[near]], z[front][inside][near]
        seen = np.abs(zb - za) < 0.1 + 0.05 * za
        counts = np.bincount(owner[front][inside][near][seen], minlength=len(sources))
    return [(int(n), int(n) / m if m else 0.0) for n, m in zip(counts, sizes, strict=True)]


def sparse_covisibility(
    target: Frame, source: Frame, T_target_source: np.ndarray, radius_px: float = 24.0
) -> tuple[int, float]:
    """How much of `source`'s scene `target`'s camera saw, given the transform between the
    two robots' maps: source's feature points, mapped and projected into target's image,
    that land near one of target's own features at a consistent depth (so neither outside
    the view nor hidden behind a nearer surface). Needs both frames' map points, poses and
    target's intrinsics. Returns (points seen, share of source's points). Many pairs:
    `covisibility_many`, with each keyframe's side prepared once."""
    if source.points is None:
        return 0, 0.0
    (out,) = covisibility_many(
        covis_target(target), [covis_source(source)], T_target_source, radius_px
    )
    return out
