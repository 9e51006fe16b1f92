"""From a rigidly placed fleet to drift-corrected trajectories and maps.

The closures (3D-3D matches, and the pairwise fits at the place database's overlaps) and
the robots' own keyframe poses go into the fleet graph (`fleetmap.fleet.graph`). A robot's
correction is applied only when it bends its map beyond the closures' noise (`min_bend_m`,
two closure sigmas): below that, the graph has seen no drift it could tell from noise and
the rigid placement stands, so a fleet without drift is merged as before.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from fleetmap.fleet.closures import Closure, ClosureParams, find_closures, refine_with_depth
from fleetmap.fleet.graph import GraphParams, Solution, optimise
from fleetmap.geometry import apply, invert
from fleetmap.mapcloud import MapCloud
from fleetmap.registration import kabsch


@dataclass(frozen=True)
class CorrectionParams:
    graph: GraphParams = field(default_factory=GraphParams)
    closure: ClosureParams = field(default_factory=ClosureParams)
    min_bend_m: float = 0.04
    # depth closures at the links, each round's ICPs started from the previous solution
    # (`link_closures`): HoloLens walk, 1 deg/m, the two fits the place database's order
    # of arrival gave: ATE 1.59 / 5.53 cm from the fit, 1.60 / 4.45 after one round from
    # the feature closures' solution, 1.55 / 1.99 after two
    link_rounds: int = 2


@dataclass
class RobotCorrection:
    """One robot's keyframes before (camera-to-map, (K, 4, 4)) and after (camera to the
    reference's map, (K, 4, 4)), their stamps (K,), the best rigid T_ref_R and how far the
    correction moved the keyframes from the rigid placement (metres)."""

    stamps: np.ndarray
    T_map_kf: np.ndarray
    T_ref_kf: np.ndarray
    rigid: np.ndarray
    applied: bool
    moved: np.ndarray
    bend_m: float
    placed: np.ndarray
    flagged: bool = False

    def T_ref_map(self, k: int) -> np.ndarray:
        """Keyframe k's own map-to-reference transform (its neighbourhood's placement)."""
        return self.T_ref_kf[k] @ invert(self.T_map_kf[k])

    def nearest(self, stamp: float) -> int:
        return int(np.abs(self.stamps - stamp).argmin())

    def frame_pose(self, stamp: float, T_map_cam: np.ndarray) -> np.ndarray:
        """A frame's corrected camera pose: the nearest keyframe's corrected pose and the
        robot's own relative motion from it."""
        return self.T_ref_map(self.nearest(stamp)) @ T_map_cam

    def summary(self) -> dict:
        return {
            "applied": self.applied,
            "moved_median_m": round(float(np.median(self.moved)), 4),
            "moved_max_m": round(float(self.moved.max()), 4),
            "bend_m": round(self.bend_m, 4),
            "flagged": self.flagged,
            "rigid_placement": self.placed.tolist(),  # T_ref_R before the correction
        }


def overlap_pairs(overlaps: list[dict], stamps: dict[str, np.ndarray]):
    """The overlaps as keyframe index pairs (robot_a, i, robot_b, j)."""
    out = set()
    for o in overlaps:
        a, b = o["robot_a"], o["robot_b"]
        if a in stamps and b in stamps:
            i = int(np.abs(stamps[a] - o["stamp_a"]).argmin())
            j = int(np.abs(stamps[b] - o["stamp_b"]).argmin())
            out.add((a, i, b, j))
    return out


def spread_links(pairs, budget: int) -> list[tuple]:
    """At most `budget` of the link pairs (robot_a, i, robot_b, j), sorted: every pair of
    robots its share (what one pair cannot use goes to the others), evenly spread over its
    keyframe pairs. An even spread over all the links gave each pair of robots a share as
    large as its links: on the drifted HoloLens walk (three robots, 1 deg/m) the second
    look's fit of A and C made 192 of the 527 links, took 22 of the 60 ICPs and kept none,
    and A stood on 6 depth closures with B (ATE 2.83 cm; 1.51 shared out; four drifted
    rows 2.03 -> 1.80 cm on average, one 1.29 -> 1.69: docs/BENCHMARKS.md, session 37)."""
    groups: dict = {}
    for q in sorted(pairs):
        groups.setdefault(tuple(sorted((q[0], q[2]))), []).append(q)
    out, left = [], budget
    for n, key in enumerate(sorted(groups, key=lambda k: (len(groups[k]), k))):
        qs = groups[key]
        take = min(len(qs), left // (len(groups) - n))
        left -= take
        out += [qs[k] for k in np.linspace(0, len(qs) - 1, take).astype(int)]
    return sorted(out)


def refined_share(closures: list[Closure], budget: int) -> set[tuple]:
    """The closures (robot_a, i, robot_b, j) to refine against depth, at most `budget`:
    every pair of robots (a robot with itself too) its share, evenly spread along it
    (`spread_links`); all of them where they are no more than the budget."""
    return set(spread_links([c.pair for c in closures], budget))


def fit_closures(pairs, poses: dict[str, np.ndarray], edges: dict) -> list[Closure]:
    """Each pairwise fit as a closure at each overlap of its pair: the keyframes' relative
    pose that the fit T_a_b implies there."""
    out = []
    for a, i, b, j in pairs:
        if (a, b) in edges:
            T_a_b, n = edges[(a, b)]["T_a_b"], edges[(a, b)]["inliers"]
        elif (b, a) in edges:
            T_a_b, n = invert(edges[(b, a)]["T_a_b"]), edges[(b, a)]["inliers"]
        else:
            continue
        T = invert(poses[a][i]) @ T_a_b @ poses[b][j]
        out.append(Closure(a, i, b, j, T, int(n), "fit"))
    return out


def drift_bound(T_map_kf: np.ndarray, p: GraphParams) -> float:
    """The largest displacement the drift model allows over the robot's path (metres)."""
    L = float(np.linalg.norm(np.diff(T_map_kf[:, :3, 3], axis=0), axis=1).sum())
    return p.scale * L + np.deg2rad(p.yaw_deg_per_m) * L * L / 2


def _bend(T_map: np.ndarray, T_ref: np.ndarray) -> tuple[np.ndarray, float]:
    """The best rigid approximation of keyframes moved from T_map to T_ref, and how far
    the farthest keyframe is from it (metres)."""
    p_map, p_ref = T_map[:, :3, 3], T_ref[:, :3, 3]
    rigid = kabsch(p_map, p_ref) if len(p_map) >= 3 else T_ref[0] @ invert(T_map[0])
    return rigid, float(np.linalg.norm(apply(rigid, p_map) - p_ref, axis=1).max())


def _robot(stamps, T_map, T_ref, T_placed, params: CorrectionParams, applied: bool | None = None):
    """One robot's correction; `applied` None: where its own map bends by `min_bend_m`."""
    p_map = T_map[:, :3, 3]
    rigid, bend = _bend(T_map, T_ref)
    applied = bend >= params.min_bend_m if applied is None else applied
    if not applied:
        T_ref, rigid = T_placed @ T_map, T_placed
    moved = np.linalg.norm(T_ref[:, :3, 3] - apply(T_placed, p_map), axis=1)
    flagged = bool(moved.max() > drift_bound(T_map, params.graph) + params.min_bend_m)
    return RobotCorrection(stamps, T_map, T_ref, rigid, applied, moved, bend, T_placed, flagged)


@dataclass
class FleetCorrection:
    """The corrected fleet: per robot its correction; the optimised graph."""

    robots: dict[str, RobotCorrection]
    solution: Solution
    keyframes: dict[str, list] = field(default_factory=dict)
    skipped: str = ""  # why no graph was built, if none was

    def cloud(self, robot: str) -> MapCloud:
        """Robot's map cloud in the reference frame, each keyframe's points by its own
        corrected placement."""
        c, kfs = self.robots[robot], self.keyframes[robot]
        pts = [apply(c.T_ref_map(k), kf.points.astype(np.float64)) for k, kf in enumerate(kfs)]
        return MapCloud(np.concatenate(pts), np.concatenate([kf.colours for kf in kfs]))

    def rigid(self, robot: str, T_ref_robot: np.ndarray) -> np.ndarray:
        """T_ref_R: the best rigid approximation of the corrected map, else as placed."""
        return self.robots[robot].rigid if robot in self.robots else T_ref_robot

    def summary(self) -> dict:
        sol = self.solution
        kinds = [c.source for c in sol.closures]
        return {
            "keyframes": int(sum(len(c.stamps) for c in self.robots.values())),
            "closures": {k: kinds.count(k) for k in ("features", "depth", "fit")},
            "intra_robot": sum(c.robot_a == c.robot_b for c in sol.closures),
            "rejected": int((sol.weights < 0.5).sum()),
            "optimise_s": round(sol.seconds, 3),
            "applied": sorted(r for r, c in self.robots.items() if c.applied),
        } | ({"skipped": self.skipped} if self.skipped else {})


def fleet_closures(
    keyframes: dict[str, list],
    placed: dict[str, np.ndarray],
    edges: dict,
    overlaps: list[dict],
    reference: str,
    params: CorrectionParams = CorrectionParams(),
) -> list[Closure]:
    """The closures `correct_fleet` optimises the fleet with (its own search)."""
    return correct_fleet(keyframes, placed, edges, overlaps, reference, params).solution.closures


def feature_closures(keyframes: dict, overlaps: list[dict], params: CorrectionParams):
    """The verified feature closures (unrefined) and the verified overlaps as keyframe
    index pairs."""
    from threadpoolctl import threadpool_limits

    frames = {r: [k.frame for k in kfs] for r, kfs in keyframes.items()}
    stamps = {r: np.array([f.stamp for f in fs]) for r, fs in frames.items()}
    pairs = overlap_pairs(by_source(overlaps, "cascade"), stamps)
    with threadpool_limits(1):  # many small problems: BLAS and OpenMP threads only contend
        return find_closures(frames, pairs, params.closure), pairs


def closures_meanwhile(keyframes: dict, overlaps: list[dict], params=CorrectionParams()):
    """`feature_closures` searched in a background thread (they need the keyframes and the
    verified overlaps, not the robots' fits: `fleetmap merge` aligns meanwhile): a future,
    or None where no robot's path can bend (`unbendable`: no graph is built)."""
    from concurrent.futures import ThreadPoolExecutor

    if unbendable(_poses({r: kfs for r, kfs in keyframes.items() if kfs}), params):
        return None
    pool = ThreadPoolExecutor(1, thread_name_prefix="closures")
    future = pool.submit(feature_closures, keyframes, overlaps, params)
    pool.shutdown(wait=False)
    return future


def _poses(keyframes: dict) -> dict[str, np.ndarray]:
    return {r: np.stack([k.frame.T_map_cam for k in kfs]) for r, kfs in keyframes.items()}


def by_source(overlaps: list[dict], source: str) -> list[dict]:
    """The overlap items of one source ("cascade": verified; "link": co-visible under a
    registered fit)."""
    return [o for o in overlaps if o.get("source", "cascade") == source]


def link_closures(
    keyframes: dict,
    overlaps: list[dict],
    poses: dict,
    edges: dict,
    params: ClosureParams,
    solved: dict[str, np.ndarray] | None = None,
    clouds: dict | None = None,
) -> list[Closure]:
    """Depth closures at the keyframe pairs co-visible under the robots' fits ("link"
    overlaps, at most `params.max_links` of them, evenly spread): the relative pose there
    (`link_trials`), refined by ICP on the two keyframes' depth clouds, kept where ICP
    overlaps well and moves it by less than `params.link_tol_m`. Few keyframe pairs of two
    robots verify by features (the HoloLens walk: 4 of 44 closures); these tie the two
    maps wherever their surfaces meet, without needing a matched feature."""
    stamps = {r: np.array([k.frame.stamp for k in kfs]) for r, kfs in keyframes.items()}
    pairs = overlap_pairs(by_source(overlaps, "link"), stamps)
    trial = link_trials(pairs, poses, edges, params, solved)
    icp = dataclasses.replace(params, tol_m=params.link_tol_m)
    refined = refine_with_depth(trial, keyframes, icp, clouds)  # `clouds`: kept by the caller
    return [c for c in refined if c.source == "depth"]


def link_trials(pairs, poses: dict, edges: dict, params: ClosureParams, solved=None):
    """Closures to refine at link pairs (robot_a, i, robot_b, j) of fitted robots, at most
    `params.max_links` (`spread_links`), each with the relative pose to start ICP from:
    the graph's where `solved` (each robot's keyframe poses in the reference frame) is
    given, else the pairwise fit's. A rigid fit of two bent maps is right where it was
    fitted and off by the bend elsewhere, beyond ICP's reach; the graph's solution is not."""
    fitted = [q for q in pairs if (q[0], q[2]) in edges or (q[2], q[0]) in edges]
    fits = fit_closures(spread_links(fitted, params.max_links), poses, edges)
    if solved is not None:
        fits = [
            dataclasses.replace(c, T_a_b=invert(solved[c.robot_a][c.i]) @ solved[c.robot_b][c.j])
            for c in fits
            if c.robot_a in solved and c.robot_b in solved
        ]
    return [dataclasses.replace(c, source="features") for c in fits]


def with_fit_closures(closures: list[Closure], pairs, poses: dict, edges: dict) -> list[Closure]:
    """The closures and, at the overlaps `pairs` (robot_a, i, robot_b, j) of robots no
    closure links, the pairwise fits as closures. A rigid fit of two bent maps is right at
    one place at best; where the robots' own keyframes verify a closure, that measures
    them exactly, drift-free (HoloLens walk, 1 deg/m: ATE 5.6 cm without fit closures,
    6.2 or 18.2 cm with them, by which overlaps the place database found)."""
    linked = {frozenset((c.robot_a, c.robot_b)) for c in closures if c.robot_a != c.robot_b}
    unlinked = {q for q in pairs if frozenset((q[0], q[2])) not in linked}
    return closures + fit_closures(unlinked, poses, edges)


def unbendable(poses: dict[str, np.ndarray], params: CorrectionParams) -> str:
    """Why no graph is worth building (no robot's path long enough for the drift model to
    bend it by `min_bend_m`: `drift_bound`), or "" where one is."""
    if all(drift_bound(T, params.graph) < params.min_bend_m for T in poses.values()):
        return f"no robot's path bends {params.min_bend_m:g} m under the drift model"
    return ""


def bends(fleet: FleetCorrection, params: CorrectionParams, found: int = 0) -> bool:
    """Whether a solution on `found` unrefined feature closures bends any map by enough
    that the depth-refined graph could apply a correction (`trigger_m`)."""
    return any(c.bend_m >= trigger_m(params, found) for c in fleet.robots.values())


def trigger_m(params: CorrectionParams, found: int) -> float:
    """The quick solution's bend (metres) from which the closures are refined against
    depth: `min_bend_m` (1 - f / 2), f the share of the refined graph's closures that the
    refinement changes (at most `max_refined` of the `found` feature closures, plus one
    round's `max_links` link closures). Where it changes them all (no more closures than
    the budget: every walk in the data), half `min_bend_m`: the refined bend has come out
    at 0.9-1.14x the quick one with drift, but on few closures also 17x a quick bend near
    zero, which the links make (SUN3D, not applied). Where it changes a few of many, the
    refined graph keeps the quick one's unrefined closures and bends as it does (robots
    that look at one place for long, no drift: TUM fr1_rpy's even and odd frames, 759
    closures, 2.25 -> 2.04 cm; the HoloLens walk's, 252, 2.21 -> 1.81 cm; docs/BENCHMARKS.md
    "Session 48")."""
    c = params.closure
    changed = (min(found, c.max_refined) + c.max_links) / (found + c.max_links)
    return params.min_bend_m * (1 - changed / 2)


def rigid_fleet(keyframes: dict, placed: dict, params: CorrectionParams, why: str):
    """Every robot as placed, no graph (`why`)."""
    out = {}
    for r, kfs in keyframes.items():
        T = np.stack([k.frame.T_map_cam for k in kfs])
        stamps = np.array([k.frame.stamp for k in kfs])
        out[r] = _robot(stamps, T, placed[r] @ T, placed[r], params)
    return FleetCorrection(out, Solution({}, np.zeros(0), 0.0), keyframes, why)


def correct_fleet(
    keyframes: dict[str, list],
    placed: dict[str, np.ndarray],
    edges: dict,
    overlaps: list[dict],
    reference: str,
    params: CorrectionParams = CorrectionParams(),
    closures: list[Closure] | None = None,
    found: tuple | None = None,
) -> FleetCorrection:
    """Drift-corrected placement of every placed robot. keyframes[R]: robot R's extracted
    keyframes in time order (`fleetmap.extract_pool.Keyframe`: frame structure with the
    camera-to-map pose and features with 3D points, map-cloud points); `closures`: the
    fleet's closures when already found (`fleet_closures`); `found`: `feature_closures` of
    these keyframes and overlaps when already searched (`closures_meanwhile`).

    Without `closures`: where no robot's path is long enough for the drift model
    (`drift_bound`: yaw per metre and scale, as the odometry edges) to bend it by
    `min_bend_m`, no correction could be applied and no graph is built (a desk seen from
    one place: TUM fr1_rpy windows paid 8-36 s for closures that changed nothing). Else
    the graph is first solved on the feature closures alone (no ICP):
    where no robot bends by `trigger_m` there (half `min_bend_m` on as many closures as
    the refinement's budget, more on many), the fleet has shown no drift the refined graph
    could apply, and the rigid placement stands at a fraction of the cost
    (the depth refinement is 60-85% of the closures' time: docs/BENCHMARKS.md "Drift")."""
    keyframes = {r: kfs for r, kfs in keyframes.items() if r in placed and kfs}
    if reference not in keyframes:
        return FleetCorrection({}, Solution({}, np.zeros(0), 0.0))
    stamps = {r: np.array([k.frame.stamp for k in kfs]) for r, kfs in keyframes.items()}
    poses = {r: np.stack([k.frame.T_map_cam for k in kfs]) for r, kfs in keyframes.items()}

    def solve(closures: list[Closure]) -> FleetCorrection:
        sol = optimise(poses, placed, closures, reference, params.graph)
        # where one map bends, every robot takes the graph's poses: a robot kept rigid
        # beside corrected ones no longer meets them (HoloLens, three robots, 0.5 deg/m:
        # B under the 4 cm gate kept rigid: 4.65 cm against a floor of 3.04)
        bent = any(_bend(poses[r], sol.poses[r])[1] >= params.min_bend_m for r in sol.poses)
        out = {
            r: _robot(stamps[r], poses[r], sol.poses[r], placed[r], params, bent) for r in sol.poses
        }
        return FleetCorrection(out, sol, keyframes)

    if closures is not None:
        return solve(closures)
    if why := unbendable(poses, params):
        return rigid_fleet(keyframes, placed, params, why)
    found, pairs = feature_closures(keyframes, overlaps, params) if found is None else found
    found = [c for c in found if c.robot_a in keyframes and c.robot_b in keyframes]
    pairs = {q for q in pairs if q[0] in keyframes and q[2] in keyframes}
    quick = solve(with_fit_closures(found, pairs, poses, edges))
    if not bends(quick, params, len(found)):
        return quick
    clouds: dict = {}  # each keyframe's cloud built once for every round's ICPs
    share = refined_share(found, params.closure.max_refined)
    refined, fleet = refine_with_depth(found, keyframes, params.closure, clouds, share), quick
    for _ in range(params.link_rounds):  # the links' ICPs from the last solution
        solved = fleet.solution.poses
        links = link_closures(keyframes, overlaps, poses, edges, params.closure, solved, clouds)
        fleet = solve(with_fit_closures(refined + links, pairs, poses, edges))
    return fleet
