"""Loop closures of the fleet graph: keyframe pairs that see the same place, within one
robot (a revisit) or between two, each with the relative pose of its cameras.

Candidates: the place database's verified overlaps, plus each keyframe's nearest GISTs
among all keyframes (the cascade's first stage; for one robot only keyframes at least
`min_gap` keyframes apart, so that a closure is not just odometry). Each candidate is
verified (`fleetmap.matching.verify_pair`, epipolar and rigid checks) and its relative pose
fitted by RANSAC over the matched features' 3D points in each camera's frame, which no
drift of the robots' maps affects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetmap.frame import Frame
from fleetmap.geometry import apply, invert, residuals
from fleetmap.matching import DEFAULT_MATCH_PARAMS, match_descriptors, verify_pair
from fleetmap.registration import ransac_rigid


@dataclass(frozen=True)
class ClosureParams:
    """Verification of a closure. The 3D tolerance is a few times a structured-light or
    time-of-flight camera's depth noise at 2-3 m (about 1 cm); `min_inliers` asks for
    twice the place database's rigid check (`MatchParams.min_rigid_inliers`)."""

    tol_m: float = 0.03
    min_inliers: int = 12
    neighbours: int = 3  # GIST candidates per keyframe
    min_gap: int = 10  # keyframes between a robot's two ends of a revisit
    floor_m: float = 0.005  # a feature point's least 3D noise (depth, keypoint position)
    # depth closures at keyframe pairs co-visible under a fit (`correct.link_closures`):
    # ICP's reach from the fit's relative pose there, which the maps' bend puts several
    # centimetres off away from the overlap it was fitted on (HoloLens walk, 1 deg/m: 3 cm
    # kept 0-2 of 60-215 such pairs, ATE 5.4 cm; 6 cm 5-42, 3.6-5.5 cm; 10 cm 10-57,
    # 1.6-2.1 cm; the floor 11.9 cm); GNC rejects the ICP that slid elsewhere
    link_tol_m: float = 0.10
    max_links: int = 60  # ICPs of two keyframe clouds (about 0.1 s each)
    # feature closures refined against depth (`refine_with_depth`), at most this many,
    # shared out as the links are (`correct.refined_share`): a robot that looks at one
    # place for long verifies a closure at nearly every pair of its keyframes (TUM fr1_rpy's
    # even and odd frames, two robots of 120: 759 closures, the graph's stage 50 s, for one that
    # then bent no map); as many as the links' two rounds, above what the walks' graphs
    # refine (HoloLens walk, two and three robots: 44-45 and 92-93, so those stay exact)
    max_refined: int = 120


@dataclass(frozen=True)
class Closure:
    """Camera j of robot_b seen from camera i of robot_a: T_a_b maps points of camera j's
    frame into camera i's (4x4). `source`: "features" (3D-3D matches) or "fit" (the
    robots' pairwise fit at this keyframe pair)."""

    robot_a: str
    i: int
    robot_b: str
    j: int
    T_a_b: np.ndarray
    inliers: int
    source: str = "features"
    information: np.ndarray | None = None  # 6x6 (rotation, translation), or fixed sigmas
    # a depth closure's surfaces (`surface_information`): which directions its ICP pinned
    surfaces: np.ndarray | None = None

    @property
    def pair(self) -> tuple[str, int, str, int]:
        """(robot_a, i, robot_b, j): the keyframe pair, as candidate and overlap pairs are."""
        return self.robot_a, self.i, self.robot_b, self.j


def camera_points(f: Frame) -> tuple[np.ndarray, np.ndarray]:
    """The frame's feature points of shape (N, 3) in its camera's frame, and their mask."""
    if f.points is None or f.T_map_cam is None:
        return np.zeros((len(f.keypoints), 3)), np.zeros(len(f.keypoints), bool)
    return apply(invert(f.T_map_cam), f.points.astype(np.float64)), f.point_valid


def relative_pose(
    fa: Frame, fb: Frame, params: ClosureParams = ClosureParams()
) -> tuple[np.ndarray, int] | None:
    """(T_cama_camb of shape (4, 4), inliers) from the two frames' matched features with
    depth, or None when the pair does not verify. The rigid RANSAC over the matches' 3D
    points runs first (cheap, and most candidates fail it); the survivors must also pass
    the epipolar verification of the place database."""
    pa, va = camera_points(fa)
    pb, vb = camera_points(fb)
    ia, ib = match_descriptors(fa.descriptors, fb.descriptors, DEFAULT_MATCH_PARAMS.ratio)
    both = va[ia] & vb[ib]
    if both.sum() < params.min_inliers:
        return None
    T, inl = ransac_rigid(pb[ib[both]], pa[ia[both]], params.tol_m)
    if inl.sum() < params.min_inliers:
        return None
    info = fit_information(T, pb[ib[both]][inl], pa[ia[both]][inl], params.floor_m)
    ver = verify_pair(
        fa.keypoints, fa.descriptors, fb.keypoints, fb.descriptors, points_a=(pa, va),
        points_b=(pb, vb), matches=(ia, ib),
    )  # fmt: skip
    return (T, int(inl.sum()), info) if ver.verified else None


def fit_information(T: np.ndarray, pb: np.ndarray, pa: np.ndarray, floor_m: float) -> np.ndarray:
    """Information (6x6, rotation then translation, GTSAM's order in camera b's frame) of a
    rigid fit pa ~ T(pb) from its inlier points: the points' scatter and their residual
    (RMS, for the fit's 6 degrees of freedom; at least `floor_m`). Few points close
    together pin the rotation loosely; a fixed sigma would take such a closure for exact
    (HoloLens walk: feature closures 2.6-6 cm and 0.6-2.1 deg from the truth)."""
    n = len(pb)
    r = residuals(T, pb, pa)
    sigma = max(float(np.sqrt((r**2).sum() / max(n - 6, 1))), floor_m)
    info = np.zeros((6, 6))
    for p in pb:
        J = np.hstack([-_skew(p), np.eye(3)])
        info += J.T @ J
    return info / sigma**2


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def gist_candidates(
    frames: dict[str, list[Frame]], params: ClosureParams = ClosureParams()
) -> set[tuple[str, int, str, int]]:
    """Keyframe pairs (robot_a, i, robot_b, j) among each keyframe's `neighbours` most
    similar GISTs (cosine) in every robot, its own keyframes only `min_gap` apart."""
    keys = [(r, i) for r, fs in frames.items() for i in range(len(fs))]
    if len(keys) < 2:
        return set()
    G = np.stack([frames[r][i].gist.astype(np.float32) for r, i in keys])
    G /= np.maximum(np.linalg.norm(G, axis=1, keepdims=True), 1e-12)
    sim = G @ G.T
    code = {r: k for k, r in enumerate(frames)}
    robot = np.array([code[r] for r, _ in keys])
    index = np.array([i for _, i in keys])
    same = robot[:, None] == robot[None, :]
    sim[same & (np.abs(index[:, None] - index[None, :]) < params.min_gap)] = -np.inf
    out = set()
    for a in range(len(keys)):
        for r in code.values():  # the nearest of every robot, own revisits included
            cols = np.flatnonzero(robot == r)
            row = sim[a, cols]
            for b in cols[np.argsort(-row)[: params.neighbours]]:
                if np.isfinite(sim[a, b]):
                    pair = sorted((keys[a], keys[int(b)]))
                    out.add((pair[0][0], pair[0][1], pair[1][0], pair[1][1]))
    return out


def find_closures(
    frames: dict[str, list[Frame]],
    pairs: set[tuple[str, int, str, int]],
    params: ClosureParams = ClosureParams(),
) -> list[Closure]:
    """The verified closures among `pairs` (robot_a, i, robot_b, j) and the GIST
    candidates."""
    out = []
    for ra, i, rb, j in sorted(pairs | gist_candidates(frames, params)):
        fit = relative_pose(frames[ra][i], frames[rb][j], params)
        if fit is not None:
            out.append(Closure(ra, i, rb, j, fit[0], fit[1], information=fit[2]))
    return out


def refine_with_depth(
    closures: list[Closure],
    keyframes: dict[str, list],
    params: ClosureParams = ClosureParams(),
    cache: dict | None = None,
    only: set[tuple] | None = None,
) -> list[Closure]:
    """Each feature closure refined by point-to-plane ICP between its two keyframes' depth
    clouds (in the cameras' frames), kept where ICP overlaps well and moves the fit by less
    than the 3D tolerance (else the feature fit stands). keyframes[R]: the extracted
    `Keyframe`s (map-cloud points in the robot's map frame); `cache`: the keyframe clouds
    built (by robot, keyframe and voxel), kept between calls by the caller; `only`: the
    closures (robot_a, i, robot_b, j) to refine, the others as they are (None: all)."""
    from threadpoolctl import threadpool_limits

    from fleetmap.mapcloud import MapCloud, icp, with_normals

    cache = {} if cache is None else cache
    voxel = params.tol_m / 2

    def cloud(r: str, i: int, normals: bool = True):
        """A keyframe's cloud, with normals where it is ICP's target (`with_normals`)."""
        if (r, i, voxel) not in cache:
            kf = keyframes[r][i]
            pts = apply(invert(kf.frame.T_map_cam), kf.points.astype(np.float64))
            cache[(r, i, voxel)] = MapCloud(pts, None).o3d(voxel, normals=False)
        pc = cache[(r, i, voxel)]
        return with_normals(pc, voxel) if normals else pc

    out = []
    # many small problems: BLAS threads only contend. Open3D 0.20's ICP reduces on its own
    # TBB threads, which this does not reach (py-spy --native; both cores busy: session 48)
    with threadpool_limits(1):
        for c in closures:
            if c.source == "features" and (only is None or c.pair in only):
                source, target = cloud(c.robot_b, c.j, normals=False), cloud(c.robot_a, c.i)
                T, fitness, _ = icp(
                    source, target, c.T_a_b, distances=(params.tol_m, params.tol_m / 2),
                    iterations=30,
                )  # fmt: skip
                D = invert(c.T_a_b) @ T
                if fitness >= 0.3 and np.linalg.norm(D[:3, 3]) < params.tol_m:
                    pins = surface_information(source, target, T, params.tol_m / 2)
                    c = Closure(c.robot_a, c.i, c.robot_b, c.j, T, c.inliers, "depth", None, pins)
            out.append(c)
    return out


def surface_information(source, target, T_a_b: np.ndarray, distance: float) -> np.ndarray | None:
    """What a point-to-plane ICP of `source` (camera b's cloud) onto `target` (camera a's,
    with normals) pinned, in GTSAM's order (rotation, translation) and camera b's frame: 3 x
    the mean of J^T J over the source points within `distance` of the target under T_a_b,
    J = [p x n, n], n the target's normal turned into b's frame (the residual n . (T p - q)
    under T Exp(xi)). A surface pins only the directions across it: a wall leaves the slide
    along it and the turn about its normal free, which fixed sigmas took for measured.
    Surfaces facing every way give the identity in translation and, at a distance z,
    z^2 about the two axes across the view: the graph divides by its `depth_m`^2, so such a
    closure keeps its 1 cm and 1 cm / z (0.3 deg at 2 m). None under 30 such points."""
    from scipy.spatial import cKDTree

    src, tgt = np.asarray(source.points), np.asarray(target.points)
    normals = np.asarray(target.normals)
    if len(src) == 0 or len(normals) != len(tgt):
        return None
    d, k = cKDTree(tgt).query(apply(T_a_b, src), distance_upper_bound=distance)
    near = np.isfinite(d)
    if near.sum() < 30:
        return None
    n_b = normals[k[near]] @ T_a_b[:3, :3]  # rows: R^T n
    J = np.hstack([np.cross(src[near], n_b), n_b])
    return 3.0 * (J.T @ J) / len(J)
