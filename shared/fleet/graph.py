"""The fleet pose graph (GTSAM): one Pose3 node per keyframe of every robot, the camera in
the reference robot's map frame.

- odometry: a robot's consecutive keyframes, their relative pose from its own trajectory,
  with sigmas that grow with the motion between them as VIO drift does (issue 22: up to
  1 deg/m of yaw and 1 % of scale), so a short step is stiff and a long one bends;
- loop closures (`fleetmap.fleet.closures`): relative camera poses from 3D-3D matches,
  within one robot and between robots (each with the information of its own inlier
  points), and the pairwise fits as closures at the place database's overlaps of robots
  that no such closure links;
- a prior on the reference robot's first keyframe (the gauge).

Robust: graduated non-convexity with a truncated least-squares loss (Yang et al. 2020, as
Kimera-Multi does), odometry known inliers, so that a wrong closure gets weight 0.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fleetmap.fleet.closures import Closure
from fleetmap.fleet.drift import up_axis
from fleetmap.geometry import invert, rotation_angle_deg
from fleetmap.lazy import LazyModule

gtsam = LazyModule("gtsam")


@dataclass(frozen=True)
class GraphParams:
    """Sigmas of the graph's edges. Odometry: the VIO drift the issue measures (yaw per
    metre, scale) plus a floor for a keyframe's own pose noise; closures: the depth noise
    of an RGB-D camera at 2-3 m (about 1-2 cm) and the rotation that lever gives."""

    yaw_deg_per_m: float = 1.0
    scale: float = 0.01
    floor_deg: float = 0.1
    floor_m: float = 0.002
    closure_m: float = 0.02
    closure_deg: float = 1.0
    depth_m: float = 0.01  # a closure refined by ICP on the depth clouds
    depth_deg: float = 0.3  # (where its surfaces are not known: 1 cm at 2 m)
    # what a depth closure says where its surfaces pin nothing (a wall's slide): a weak
    # prior, so that its information stays invertible; the odometry decides there
    slide_m: float = 0.1
    slide_deg: float = 5.0
    inlier_probability: float = 0.99  # GNC's chi-square inlier threshold


@dataclass
class Solution:
    """The optimised graph: corrected camera-to-reference poses per robot, of shape
    (K, 4, 4); each closure's GNC weight (1 inlier, 0 rejected); the time taken."""

    poses: dict[str, np.ndarray]
    weights: np.ndarray
    seconds: float
    graph: object = None
    values: object = None
    closures: list = field(default_factory=list)

    def write_g2o(self, path) -> None:
        """The keyframe graph in g2o's SE3 format (GTSAM's writer): the optimised poses,
        odometry and the closures GNC kept (a rejected one is left out)."""
        if self.graph is None:
            return
        kept = gtsam.NonlinearFactorGraph()
        n_known = self.graph.size() - len(self.weights)
        for k in range(self.graph.size()):
            factor = self.graph.at(k)
            if k >= n_known and self.weights[k - n_known] < 0.5:
                continue
            if isinstance(factor, gtsam.BetweenFactorPose3):
                kept.add(factor)
        gtsam.writeG2o(kept, self.values, str(path))

    def g2o_text(self) -> str | None:
        """`write_g2o`'s file as text (None without a graph): what the live map stores."""
        if self.graph is None:
            return None
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "pose_graph.g2o"
            self.write_g2o(path)
            return path.read_text()


class FleetGraph:
    """Node numbering and factors of one fleet's keyframe graph.

    poses[R]: robot R's keyframes' camera-to-map poses of shape (K, 4, 4), in time order;
    placed[R]: T_ref_R, the rigid placement that gives the initial values."""

    def __init__(self, poses: dict[str, np.ndarray], placed: dict[str, np.ndarray]):
        self.robots = [r for r in poses if r in placed]
        self.poses, self.placed = poses, placed
        self.offset, n = {}, 0
        for r in self.robots:
            self.offset[r] = n
            n += len(poses[r])
        self.size = n

    def node(self, robot: str, i: int) -> int:
        return self.offset[robot] + i

    def initial(self):
        values = gtsam.Values()
        for r in self.robots:
            for i, T in enumerate(self.poses[r]):
                values.insert(self.node(r, i), gtsam.Pose3(self.placed[r] @ T))
        return values

    def odometry(self, graph, p: GraphParams) -> None:
        for r in self.robots:
            P = self.poses[r]
            up = up_axis(P)
            for i in range(1, len(P)):
                T = invert(P[i - 1]) @ P[i]
                noise = gtsam.noiseModel.Gaussian.Covariance(odometry_covariance(T, P[i], up, p))
                a, b = self.node(r, i - 1), self.node(r, i)
                graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(T), noise))

    def closures(self, graph, closures: list[Closure], p: GraphParams) -> None:
        for c in closures:
            m, deg = (
                (p.depth_m, p.depth_deg) if c.source == "depth" else (p.closure_m, p.closure_deg)
            )
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([np.deg2rad(deg)] * 3 + [m] * 3))
            if c.information is not None and c.source == "features":
                noise = gtsam.noiseModel.Gaussian.Information(c.information)
            if c.surfaces is not None and c.source == "depth":
                noise = gtsam.noiseModel.Gaussian.Information(depth_information(c.surfaces, p))
            a, b = self.node(c.robot_a, c.i), self.node(c.robot_b, c.j)
            graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(c.T_a_b), noise))


def depth_information(surfaces: np.ndarray, p: GraphParams) -> np.ndarray:
    """A depth closure's information (6x6): what its surfaces pinned
    (`closures.surface_information`) at the depth noise `depth_m`, plus the weak
    `slide_deg` / `slide_m` in every direction. Point-to-plane ICP of two keyframes on the
    HoloLens walk, eight drifted draws (0.5 and 1 deg/m, two and three robots): ATE 1.83
    -> 1.75 cm on average, 5 better and 3 worse; the three-robot walk at 0.5 deg/m 1.59 /
    1.55 -> 1.41 / 1.28 cm (docs/BENCHMARKS.md, session 20)."""
    slide = np.array([np.deg2rad(p.slide_deg)] * 3 + [p.slide_m] * 3)
    return surfaces / p.depth_m**2 + np.diag(1.0 / slide**2)


def odometry_covariance(
    T_step: np.ndarray, T_map_cam: np.ndarray, up: np.ndarray, p: GraphParams
) -> np.ndarray:
    """6x6 covariance (rotation, translation; in the camera's frame, GTSAM's order) of
    one odometry step T_step ending at camera pose T_map_cam: VIO sees gravity, so yaw
    about `up` (map frame) drifts with the distance moved while roll and pitch keep the
    floor; translation drifts in scale."""
    d = float(np.linalg.norm(T_step[:3, 3]))
    u = T_map_cam[:3, :3].T @ up
    yaw = np.deg2rad(p.floor_deg + p.yaw_deg_per_m * d)
    level = np.deg2rad(p.floor_deg)
    cov = np.zeros((6, 6))
    cov[:3, :3] = yaw**2 * np.outer(u, u) + level**2 * (np.eye(3) - np.outer(u, u))
    cov[3:, 3:] = np.eye(3) * (p.floor_m + p.scale * d) ** 2
    return cov


def usable(closures: list[Closure], poses: dict[str, np.ndarray]) -> list[Closure]:
    """Closures whose two keyframes are both in the graph."""
    return [
        c
        for c in closures
        if c.robot_a in poses
        and c.robot_b in poses
        and c.i < len(poses[c.robot_a])
        and c.j < len(poses[c.robot_b])
    ]


def optimise(
    poses: dict[str, np.ndarray],
    placed: dict[str, np.ndarray],
    closures: list[Closure],
    reference: str,
    params: GraphParams = GraphParams(),
) -> Solution:
    """Build the graph and optimise it with GNC (TLS loss; odometry and the prior known
    inliers). Robots not in `placed` are left out."""
    t0 = time.perf_counter()
    fg = FleetGraph(poses, placed)
    closures = usable(closures, {r: poses[r] for r in fg.robots})
    graph = gtsam.NonlinearFactorGraph()
    tiny = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    anchor = gtsam.Pose3(placed[reference] @ poses[reference][0])
    graph.add(gtsam.PriorFactorPose3(fg.node(reference, 0), anchor, tiny))
    fg.odometry(graph, params)
    n_known = graph.size()
    fg.closures(graph, closures, params)
    initial = fg.initial()
    values = initial
    weights = np.ones(len(closures))
    if closures:
        own = [k for k, c in enumerate(closures) if c.robot_a == c.robot_b]
        kept_own = _own_inliers(fg, graph, own, initial, n_known, params)
        values, weights = _gnc(graph, initial, list(range(n_known)) + kept_own, params)
        weights = weights[n_known:]
    out = {
        r: np.stack([values.atPose3(fg.node(r, i)).matrix() for i in range(len(poses[r]))])
        for r in fg.robots
    }
    return Solution(out, weights, time.perf_counter() - t0, graph, values, closures)


def _gnc(graph, initial, known: list[int], params: GraphParams):
    """GNC (TLS loss) over `graph` with the factors `known` held as inliers: (values, the
    weight of every factor)."""
    gp = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    gp.setLossType(gtsam.GncLossType.TLS)
    gp.setKnownInliers(known)
    # GNC starts from the non-robust optimum; computed here with plain LM from the rigid
    # placement, GNC's own first solve is already converged (0.5 s for 2,000 keyframes
    # instead of 1.3 s, the same closures rejected on the HoloLens walk)
    lm = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    opt = gtsam.GncLMOptimizer(graph, lm.optimize(), gp)
    opt.setInlierCostThresholdsAtProbability(params.inlier_probability)
    values = opt.optimize()
    return values, np.asarray(opt.getWeights())


def _own_inliers(fg, graph, own: list[int], initial, n_known: int, params) -> list[int]:
    """Factor indices (in `graph`) of the robots' own loop closures that GNC keeps on the
    robots' own graphs (each robot's odometry, its first keyframe held, and its own
    closures), judged before any closure between robots: one wrong closure between robots
    (a look-alike place 0.5 m and 10 deg off) otherwise took a robot's own revisit and two
    right closures between robots down with it (drifted HoloLens walk with 7 closures
    between the robots: ATE 15.5 cm against 2.3 cm without it; session 13)."""
    if not own:
        return []
    sub = gtsam.NonlinearFactorGraph()
    tiny = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for r in fg.robots:
        sub.add(gtsam.PriorFactorPose3(fg.node(r, 0), initial.atPose3(fg.node(r, 0)), tiny))
    for k in range(1, n_known):  # the odometry (factor 0 is the reference's prior)
        sub.add(graph.at(k))
    known = sub.size()
    for k in own:
        sub.add(graph.at(n_known + k))
    _, w = _gnc(sub, initial, list(range(known)), params)
    return [n_known + k for k, wk in zip(own, w[known:], strict=True) if wk >= 0.5]


def closure_residuals(sol_poses: dict[str, np.ndarray], closures: list[Closure]) -> np.ndarray:
    """Per closure (translation m, rotation deg) disagreement with the given poses, shape
    (C, 2)."""
    out = []
    for c in closures:
        T = invert(sol_poses[c.robot_a][c.i]) @ sol_poses[c.robot_b][c.j]
        E = invert(c.T_a_b) @ T
        out.append((np.linalg.norm(E[:3, 3]), rotation_angle_deg(E[:3, :3])))
    return np.array(out).reshape(-1, 2)
