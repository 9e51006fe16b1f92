"""The live map's keyframe graph (issue 22): every placed robot's keyframes in one robust
pose graph, solved again as keyframes, closures and fits arrive, as `fleetmap merge`
solves it once (`fleetmap.fleet.correct`: the same closures, rules and graph).

Work is kept between solves: a keyframe's frame is read once, a candidate keyframe pair
verified once (its closure or None) and refined against the two views' depth once (only
while the unrefined graph bends a map). A step judges candidates for at most `budget_s`,
so the merge worker is never held long; the graph is solved once every candidate of the
present keyframes is judged. The solution is stored as the "graph" row
(`fleetmap.fleet.state`) with the placement version it was solved on: every replica serves
the same corrected trajectories and cloud (`StoredCorrection`), and a placement that
changed leaves it stale, unserved, until it is solved again.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from fleetmap.fleet.closures import Closure, gist_candidates, refine_with_depth, relative_pose
from fleetmap.fleet.correct import (
    CorrectionParams,
    FleetCorrection,
    bends,
    correct_fleet,
    link_trials,
    refined_share,
    rigid_fleet,
    unbendable,
    with_fit_closures,
)
from fleetmap.fleet.merge_rules import merged_edges
from fleetmap.fleet.state import read_graph, write_graph
from fleetmap.fleet.types import Placement
from fleetmap.fleet.view_choice import look_at
from fleetmap.frame import Frame
from fleetmap.geometry import transform_error

log = logging.getLogger(__name__)


@dataclass
class StoredKeyframe:
    """A stored keyframe as the graph reads it: its frame, and its view's share of the map
    cloud in its robot's map frame (decoded on each use, never kept: a fleet's views
    would not fit in memory)."""

    db: object
    kf_id: int
    frame: Frame

    @property
    def points(self) -> np.ndarray:
        from fleetmap.fleet.map_render import view_cloud
        from fleetmap.view import stored_view

        return view_cloud(stored_view(self.frame, *self.db.view_bytes(self.kf_id)))[0]


class LiveGraph:
    """The keyframe graph of the live map's placed robots, kept up to date step by step."""

    def __init__(
        self,
        db,
        params: CorrectionParams | None = None,
        budget_s: float = 1.0,
        interval_s: float = 5.0,
    ):
        self.db, self.params, self.budget_s = db, params or CorrectionParams(), budget_s
        self.interval_s = interval_s  # between steps on one placement (keyframes streaming)
        self._last: tuple[int, float] = (-1, 0.0)  # placement version, time of the last step
        self._frames: dict[int, Frame | None] = {}  # keyframe id -> frame (None: no pose)
        self._judged: dict[tuple[int, int], Closure | None] = {}  # ids (a, b) -> closure
        self._refined: dict[tuple[int, int], Closure] = {}
        # ids -> (ICP's start, the depth closure it gave or None)
        self._linked: dict[tuple, tuple] = {}
        self._solved: tuple | None = None

    def step(self, placement: Placement, states: dict) -> bool:
        """Judge candidates for up to `budget_s`; once all are judged, solve the graph and
        store it. True when a new solution was stored. On an unchanged placement, a step
        comes `interval_s` after the last solve at the earliest."""
        now = time.monotonic()
        if placement.version == self._last[0] and now - self._last[1] < self.interval_s:
            return False
        ids = {r: self._posed(r) for r in placement.T_ref}
        ids = {r: v for r, v in ids.items() if v}
        if placement.reference not in ids:
            return False
        edges = merged_edges(states, set(ids))
        key = (
            placement.version,
            tuple(sorted((r, len(v)) for r, v in ids.items())),
            tuple(sorted((a, b, e["inliers"]) for (a, b), e in edges.items())),
        )
        if key == self._solved:
            return False
        kfs = {r: [StoredKeyframe(self.db, k, self._frames[k]) for k in v] for r, v in ids.items()}
        fleet = self._solve(kfs, placement, edges, now + self.budget_s)
        if fleet is None:
            return False
        write_graph(self.db, graph_row(placement.version, fleet, ids), fleet.solution.g2o_text())
        self._solved, self._last = key, (placement.version, time.monotonic())
        log.info("live map: keyframe graph of %d robots solved %s", len(ids), fleet.summary())
        return True

    def hold(self, version: int) -> None:
        """No step on this placement for `interval_s` (after a step failed)."""
        self._last = (version, time.monotonic())

    def _solve(self, kfs: dict, placement: Placement, edges: dict, deadline: float):
        """The corrected fleet, or None while candidates or refinements are left."""
        placed, ref = placement.T_ref, placement.reference
        poses = {r: np.stack([k.frame.T_map_cam for k in v]) for r, v in kfs.items()}
        if why := unbendable(poses, self.params):
            return rigid_fleet(kfs, placed, self.params, why)
        index = {k.kf_id: (r, i) for r, v in kfs.items() for i, k in enumerate(v)}
        if not self._judge(self._candidates(kfs), deadline):
            return None
        found = [self._indexed(c, index) for c in self._present(index)]
        overlap_pairs = self._overlap_pairs(kfs, index)
        fleet = correct_fleet(
            kfs, placed, edges, [], ref, self.params,
            closures=with_fit_closures(found, overlap_pairs, poses, edges),
        )  # fmt: skip
        if not bends(fleet, self.params, len(found)):
            return fleet
        if not self._refine(kfs, index, deadline):
            return None
        present = self._present(index)
        refined = [self._indexed(self._refined.get(self._key(c), c), index) for c in present]
        for _ in range(self.params.link_rounds):  # the links' ICPs from the last solution
            links = self._links(kfs, poses, edges, deadline, fleet.solution.poses)
            if links is None:
                return None
            fleet = correct_fleet(
                kfs, placed, edges, [], ref, self.params,
                closures=with_fit_closures(refined + links, overlap_pairs, poses, edges),
            )  # fmt: skip
        return fleet

    # --- keyframes and candidates -------------------------------------------------------

    def _posed(self, robot: str) -> list[int]:
        """The robot's keyframe ids with a pose, in time order (frames read once)."""
        out = []
        for k in self.db.keyframe_ids(robot):
            if k not in self._frames:
                f = self.db.load_frame(k)
                self._frames[k] = f if f.T_map_cam is not None else None
            if self._frames[k] is not None:
                out.append(k)
        return out

    def _candidates(self, kfs: dict) -> list[tuple[int, int]]:
        """Keyframe id pairs to judge: the cascade's overlaps and the GIST candidates."""
        frames = {r: [k.frame for k in v] for r, v in kfs.items()}
        pairs = {(kfs[a][i].kf_id, kfs[b][j].kf_id) for a, i, b, j in gist_candidates(frames)}
        robots = sorted(kfs)
        for x, a in enumerate(robots):
            for b in robots[x + 1 :]:
                pairs |= {(o.kf_a, o.kf_b) for o in self._cascade(a, b)}
        return sorted(self._key_of(*p) for p in pairs)

    def _cascade(self, a: str, b: str) -> list:
        return [o for o in self.db.overlaps(a, b) if o.source == "cascade"]

    def _overlap_pairs(self, kfs: dict, index: dict) -> set:
        """The cascade's overlaps as keyframe index pairs (robot_a, i, robot_b, j)."""
        out, robots = set(), sorted(kfs)
        for x, a in enumerate(robots):
            for b in robots[x + 1 :]:
                for o in self._cascade(a, b):
                    if o.kf_a in index and o.kf_b in index:
                        out.add((*index[o.kf_a], *index[o.kf_b]))
        return out

    def _judge(self, pairs: list[tuple[int, int]], deadline: float) -> bool:
        """Verify the pairs not judged yet until the deadline; True when all are."""
        for p in pairs:
            if p in self._judged:
                continue
            if time.monotonic() > deadline:
                return False
            fa, fb = self._frames[p[0]], self._frames[p[1]]
            fit = relative_pose(fa, fb, self.params.closure)
            self._judged[p] = None
            if fit is not None:
                self._judged[p] = Closure("", p[0], "", p[1], fit[0], fit[1], information=fit[2])
        return True

    def _refine(self, kfs: dict, index: dict, deadline: float) -> bool:
        """Refine the present feature closures against depth until the deadline (both
        keyframes need a stored view), at most `max_refined` of them (`refined_share`, as
        `fleetmap merge` chooses them; those refined earlier stay refined); True when all
        are."""
        viewed = {k for r in kfs for k in self.db.view_ids(r)}
        present = self._present(index)
        indexed = [self._indexed(c, index) for c in present]
        share = refined_share(indexed, self.params.closure.max_refined)
        for c, at in zip(present, indexed, strict=True):
            p = self._key(c)
            if p in self._refined or at.pair not in share:
                continue
            if time.monotonic() > deadline:
                return False
            self._refined[p] = c
            if p[0] in viewed and p[1] in viewed:
                done = self._icp(p, c, self.params.closure)
                self._refined[p] = dataclasses.replace(c, T_a_b=done.T_a_b, source=done.source)
        return True

    def _icp(self, p: tuple[int, int], c: Closure, params) -> Closure:
        """Closure `c` between keyframes p refined against their stored views' depth."""
        one = {"a": [StoredKeyframe(self.db, p[0], self._frames[p[0]])]}
        one["b"] = [StoredKeyframe(self.db, p[1], self._frames[p[1]])]
        trial = dataclasses.replace(c, robot_a="a", i=0, robot_b="b", j=0)
        return refine_with_depth([trial], one, params)[0]

    def _links(self, kfs: dict, poses: dict, edges: dict, deadline: float, solved: dict):
        """The depth closures at the keyframe pairs co-visible under the robots' fits, ICP
        started from the `solved` graph's poses (as `fleetmap.fleet.correct.link_closures`),
        each start tried once; None while some are left at the deadline."""
        index = {k.kf_id: (r, i) for r, v in kfs.items() for i, k in enumerate(v)}
        viewed = {k for r in kfs for k in self.db.view_ids(r)}
        pairs, robots = set(), sorted(kfs)
        for x, a in enumerate(robots):
            for b in robots[x + 1 :]:
                for o in self.db.overlaps(a, b):
                    if o.source == "link" and {o.kf_a, o.kf_b} <= viewed:
                        if o.kf_a in index and o.kf_b in index:
                            pairs.add((*index[o.kf_a], *index[o.kf_b]))
        cp = self.params.closure
        fits = link_trials(pairs, poses, edges, cp, solved)  # `spread_links` orders them
        icp, out = dataclasses.replace(cp, tol_m=cp.link_tol_m), []
        for c in fits:
            ids = (kfs[c.robot_a][c.i].kf_id, kfs[c.robot_b][c.j].kf_id)
            start, done = self._linked.get(ids, (None, None))
            if start is None or not _near(start, c.T_a_b):  # ICP from elsewhere: again
                if time.monotonic() > deadline:
                    return None
                refined = self._icp(ids, c, icp)
                start, done = c.T_a_b, refined if refined.source == "depth" else None
                self._linked[ids] = start, done
            if done is not None:
                out.append(dataclasses.replace(c, T_a_b=done.T_a_b, source="depth",
                                               surfaces=done.surfaces))  # fmt: skip
        return out

    def _present(self, index: dict) -> list[Closure]:
        """The verified closures between keyframes of the present graph."""
        judged = self._judged.items()
        return [c for p, c in judged if c is not None and p[0] in index and p[1] in index]

    @staticmethod
    def _key(c: Closure) -> tuple[int, int]:
        return c.i, c.j

    @staticmethod
    def _key_of(a: int, b: int) -> tuple[int, int]:
        return (a, b) if a < b else (b, a)

    @staticmethod
    def _indexed(c: Closure, index: dict) -> Closure:
        (ra, i), (rb, j) = index[c.i], index[c.j]
        return dataclasses.replace(c, robot_a=ra, i=i, robot_b=rb, j=j)


def graph_row(version: int, fleet: FleetCorrection, ids: dict[str, list[int]]) -> dict:
    """The stored solution: the placement version it was solved on, the graph's figures,
    per robot its correction's figures and, where applied, each keyframe's stamp, look-at
    point (its map frame) and corrected map-to-reference transform (3x4, row-major)."""
    robots = {}
    for r, c in fleet.robots.items():
        row = c.summary() | {"rigid": np.round(c.rigid, 6).tolist()}
        if c.applied:
            T = np.stack([c.T_ref_map(k) for k in range(len(c.stamps))])
            row["stamps"] = c.stamps.tolist()
            row["looks"] = np.round([look_at(P) for P in c.T_map_kf], 4).tolist()
            row["T_ref_map"] = np.round(T[:, :3, :].reshape(len(T), 12), 6).tolist()
        robots[r] = row
    summary = fleet.summary() | {"solved_at": time.time()}
    return {"version": version, "summary": summary, "robots": robots}


@dataclass
class StoredCorrection:
    """A robot's stored correction: per keyframe its stamp (K,), look-at point (K, 3) and
    map-to-reference transform (K, 4, 4)."""

    stamps: np.ndarray
    looks: np.ndarray
    T_ref_map: np.ndarray

    def pose(self, stamp: float, T_map_cam: np.ndarray) -> np.ndarray:
        """A camera pose corrected as its nearest keyframe in time."""
        return self.T_ref_map[int(np.abs(self.stamps - stamp).argmin())] @ T_map_cam

    def warp(self, pts: np.ndarray) -> np.ndarray:
        """Map points (N, 3) into the reference frame, each as the keyframe whose look-at
        point is nearest (the keyframe that most likely saw it)."""
        from scipy.spatial import cKDTree

        if not len(pts):
            return pts
        _, k = cKDTree(self.looks).query(pts)
        T = self.T_ref_map[k]
        return np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]


def stored_corrections(db, version: int) -> tuple[dict[str, StoredCorrection], dict | None]:
    """The applied corrections of the graph solved on placement `version`, by robot, and
    the stored row (None when there is none for this version)."""
    g = read_graph(db)
    if g is None or g["version"] != version:
        return {}, None
    out = {}
    for r, row in g["robots"].items():
        if row.get("applied") and "T_ref_map" in row:
            T = np.tile(np.eye(4), (len(row["stamps"]), 1, 1))
            T[:, :3, :] = np.asarray(row["T_ref_map"]).reshape(-1, 3, 4)
            out[r] = StoredCorrection(np.asarray(row["stamps"]), np.asarray(row["looks"]), T)
    return out, g


def _near(T: np.ndarray, U: np.ndarray, metres: float = 0.005, radians: float = 0.005) -> bool:
    """Two relative poses close enough that ICP started from either ends the same."""
    dt, dr = transform_error(U, T)
    return dt < metres and dr < np.degrees(radians)
