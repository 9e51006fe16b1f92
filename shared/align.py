"""The default alignment of two robots' maps from matched RGB-D pairs, with a quality gate.

1. Pool 3D-3D correspondences over the pairs (`shared.correspondences`).
2. Rigid hypotheses by sequential RANSAC: the best consensus, then the best among what is
   left, and so on. Look-alike places (rows of identical cubicles) give consistent but
   wrong consensus sets, so the largest one is not trusted blindly.
3. Each hypothesis refined by point-to-plane ICP on the two robots' map clouds and scored
   by geometric overlap; the best wins.
4. The gate: enough inlier correspondences, enough spread, a small held-out residual (each
   fold of inliers predicted by a fit on the others), and no rival hypothesis far away with
   nearly the same overlap. Otherwise: no merge, with the reason.
5. An MLP (the thesis's estimator) on the inliers, kept only where it lowers the held-out
   error of the rigid fit.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from shared.correspondences import Correspondences, RGBDView, pooled_correspondences
from shared.errors import BadInput
from shared.estimators import MLPEstimator, fit_affine
from shared.geometry import apply, transform_error
from shared.mapcloud import icp, overlap_fitness, views_cloud
from shared.registration import kabsch, ransac_rigid

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AlignParams:
    """Gate thresholds in metres; `hypotheses` rigid consensus sets are compared."""

    ransac_tol_m: float = 0.08
    min_inliers: int = 12
    min_spread_m: float = 0.15
    max_holdout_m: float = 0.08
    hypotheses: int = 6
    voxel_m: float = 0.03
    ambiguity: float = 0.9  # a rival with this share of the best overlap makes it ambiguous
    rival_m: float = 0.3
    rival_deg: float = 10.0
    use_icp: bool = True
    try_mlp: bool = True


@dataclass
class Hypothesis:
    T_a_b: np.ndarray
    support: int
    fitness: float = 0.0


@dataclass
class AlignResult:
    """Outcome: merged or not (with the reason), T_a_b maps B's map frame into A's."""

    merged: bool
    reason: str
    T_a_b: np.ndarray | None = None
    method: str = ""
    correspondences: int = 0
    inliers: int = 0
    holdout_m: float = float("nan")
    fitness: float = 0.0
    mlp_holdout_m: float | None = None
    mlp: MLPEstimator | None = field(default=None, repr=False)
    hypotheses: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        d = {
            "merged": self.merged,
            "reason": self.reason,
            "method": self.method,
            "correspondences": self.correspondences,
            "inliers": self.inliers,
            "holdout_residual_m": _num(self.holdout_m),
            "icp_fitness": self.fitness,
            "mlp_holdout_residual_m": _num(self.mlp_holdout_m),
            "hypotheses": self.hypotheses,
            "seconds": self.seconds,
        }
        if self.T_a_b is not None:
            d["transform"] = self.T_a_b.tolist()
        if self.mlp is not None:
            d["affine"] = self.mlp.affine_.tolist()
        return d

    def map_points(self, points_b: np.ndarray) -> np.ndarray:
        """B's map points into A's frame with the chosen model."""
        if self.mlp is not None:
            return self.mlp.transform(points_b)
        return apply(self.T_a_b, points_b)


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


def holdout_residual(
    X: np.ndarray, Y: np.ndarray, folds: int = 5, seed: int = 0, model: str = "rigid"
) -> float:
    """Median residual of each fold predicted by a fit on the other folds (metres)."""
    n = len(X)
    if n < 2 * folds:
        return float("inf")
    order = np.random.default_rng(seed).permutation(n)
    res = []
    for k in range(folds):
        test = order[k::folds]
        train = np.setdiff1d(order, test)
        if model == "rigid":
            T = kabsch(X[train], Y[train])
            res.append(np.linalg.norm(apply(T, X[test]) - Y[test], axis=1))
        else:
            est = MLPEstimator(max_epochs=200, random_state=seed).fit(X[train], Y[train])
            res.append(np.linalg.norm(est.transform(X[test]) - Y[test], axis=1))
    return float(np.median(np.concatenate(res)))


def spread(points: np.ndarray) -> float:
    """Second-largest standard deviation of a point set: small for a line or a spot."""
    if len(points) < 3:
        return 0.0
    w = np.linalg.eigvalsh(np.cov(points.T))
    return float(np.sqrt(max(w[-2], 0.0)))


def rigid_hypotheses(C: Correspondences, p: AlignParams) -> list[Hypothesis]:
    """Sequential RANSAC: disjoint consensus sets, largest first."""
    X, Y = C.X, C.Y
    left = np.ones(len(X), bool)
    out = []
    for k in range(p.hypotheses):
        if left.sum() < p.min_inliers:
            break
        idx = np.flatnonzero(left)
        T, inl = ransac_rigid(X[idx], Y[idx], p.ransac_tol_m, iterations=2000, seed=k)
        if inl.sum() < max(3, p.min_inliers // 2):
            break
        out.append(Hypothesis(T, int(inl.sum())))
        left[idx[inl]] = False
    return out


def align_views(
    pairs: list[tuple[RGBDView, RGBDView]],
    p: AlignParams = AlignParams(),
    correspondences: Correspondences | None = None,
) -> AlignResult:
    """Fit T_a_b from RGB-D pairs (view of robot A, view of robot B); gate it."""
    t0 = time.perf_counter()
    if not pairs:
        raise BadInput("Give at least one RGB-D pair")
    C = correspondences if correspondences is not None else pooled_correspondences(pairs)
    res = _align(C, pairs, p)
    res.correspondences = len(C)
    res.seconds = time.perf_counter() - t0
    log.info(
        "alignment: merged=%s (%s), %d correspondences, %.1f s",
        res.merged,
        res.reason,
        len(C),
        res.seconds,
    )
    return res


def _align(C: Correspondences, pairs, p: AlignParams) -> AlignResult:
    if len(C) < p.min_inliers:
        return AlignResult(
            False, f"only {len(C)} correspondences with depth (need {p.min_inliers})"
        )
    hyps = rigid_hypotheses(C, p)
    if not hyps:
        return AlignResult(False, "no rigid consensus among the correspondences")
    if p.use_icp:
        cloud_a = views_cloud([a for a, _ in _unique(pairs, 0)], voxel=p.voxel_m)
        cloud_b = views_cloud([b for _, b in _unique(pairs, 1)], voxel=p.voxel_m)
        for h in hyps:
            h.T_a_b, _, _ = icp(
                cloud_b, cloud_a, h.T_a_b, distances=(5 * p.voxel_m, 2 * p.voxel_m, p.voxel_m)
            )
            h.fitness = overlap_fitness(cloud_b, cloud_a, h.T_a_b, 2 * p.voxel_m)
        hyps.sort(key=lambda h: -h.fitness)
    best = hyps[0]
    summary = [{"support": h.support, "icp_fitness": h.fitness} for h in hyps]
    resid = np.linalg.norm(apply(best.T_a_b, C.X) - C.Y, axis=1)
    inl = resid < p.ransac_tol_m
    n_inl = int(inl.sum())
    out = AlignResult(
        False,
        "",
        best.T_a_b,
        "rigid+icp" if p.use_icp else "rigid",
        inliers=n_inl,
        fitness=best.fitness,
        hypotheses=summary,
    )
    for h in hyps[1:]:
        dt, dr = transform_error(h.T_a_b, best.T_a_b)
        if (dt > p.rival_m or dr > p.rival_deg) and h.fitness >= p.ambiguity * best.fitness:
            out.reason = (
                f"ambiguous: a rival alignment {dt:.2f} m / {dr:.0f} deg away fits "
                f"{h.fitness:.2f} of the map against {best.fitness:.2f}"
            )
            return out
    if n_inl < p.min_inliers:
        out.reason = f"{n_inl} inlier correspondences (need {p.min_inliers})"
        return out
    sp = spread(C.X[inl])
    if sp < p.min_spread_m:
        out.reason = f"inliers spread {sp:.2f} m (need {p.min_spread_m})"
        return out
    out.holdout_m = holdout_residual(C.X[inl], C.Y[inl])
    if not out.holdout_m <= p.max_holdout_m:
        out.reason = f"held-out residual {out.holdout_m:.3f} m (max {p.max_holdout_m})"
        return out
    if p.try_mlp and n_inl >= 30:
        out.mlp_holdout_m = holdout_residual(C.X[inl], C.Y[inl], model="mlp")
        if out.mlp_holdout_m < 0.9 * out.holdout_m:
            out.mlp = MLPEstimator().fit(C.X[inl], C.Y[inl])
            out.method += "+mlp"
    out.merged, out.reason = True, "passed the quality gate"
    return out


def _unique(pairs, side: int):
    seen, out = set(), []
    for pr in pairs:
        v = pr[side]
        if id(v) not in seen:
            seen.add(id(v))
            out.append(pr)
    return out


ROBOT_COLOURS = np.array(
    [
        [0.85, 0.25, 0.2],
        [0.2, 0.45, 0.9],
        [0.3, 0.7, 0.3],
        [0.9, 0.7, 0.1],
        [0.6, 0.3, 0.8],
        [0.1, 0.7, 0.8],
        [0.9, 0.4, 0.6],
        [0.5, 0.5, 0.5],
    ]
)


def baseline(pairs, method: str, p: AlignParams) -> AlignResult:
    """One estimator alone, for comparison: closed form or MLP on the pooled visual
    correspondences, or ICP from identity on the map clouds (the thesis's ICP baseline)."""
    from shared.estimators import AffineEstimator, RigidEstimator, SimilarityEstimator

    t0 = time.perf_counter()
    if method == "icp":
        ca = views_cloud([a for a, _ in _unique(pairs, 0)], voxel=p.voxel_m)
        cb = views_cloud([b for _, b in _unique(pairs, 1)], voxel=p.voxel_m)
        T, fit, rmse = icp(cb, ca, np.eye(4))
        return AlignResult(
            True,
            "ICP from identity (no gate)",
            T,
            "icp",
            fitness=fit,
            seconds=time.perf_counter() - t0,
        )
    C = pooled_correspondences(pairs)
    est = {
        "rigid": RigidEstimator,
        "similarity": SimilarityEstimator,
        "affine": AffineEstimator,
    }.get(method)
    if est is not None:
        e = est(threshold=p.ransac_tol_m).fit(C.X, C.Y)
        return AlignResult(
            True,
            f"{method} in RANSAC (no gate)",
            e.T_,
            method,
            len(C),
            int(e.inliers_.sum()),
            seconds=time.perf_counter() - t0,
        )
    if method == "mlp":
        m = MLPEstimator().fit(C.X, C.Y)
        return AlignResult(
            True,
            "thesis MLP (no gate)",
            m.affine_,
            "mlp",
            len(C),
            len(C),
            mlp=m,
            seconds=time.perf_counter() - t0,
        )
    raise BadInput(f"Unknown method {method!r}")


def merged_cloud(
    pairs, result: AlignResult, colour: str = "robot", voxel: float = 0.03
) -> tuple[np.ndarray, np.ndarray]:
    """A's views and B's views mapped into A's frame: points (N, 3) and colours (N, 3)."""
    ca = views_cloud([a for a, _ in _unique(pairs, 0)], voxel=voxel)
    cb = views_cloud([b for _, b in _unique(pairs, 1)], voxel=voxel)
    pa, pb = np.asarray(ca.points), result.map_points(np.asarray(cb.points))
    if colour == "image" and ca.has_colors() and cb.has_colors():
        cols = np.concatenate([np.asarray(ca.colors), np.asarray(cb.colors)])
    else:
        cols = np.concatenate(
            [np.tile(ROBOT_COLOURS[0], (len(pa), 1)), np.tile(ROBOT_COLOURS[1], (len(pb), 1))]
        )
    return np.concatenate([pa, pb]), cols


def align_request(
    pairs, method: str, p: AlignParams, want_cloud: bool = False, colour: str = "robot"
) -> tuple[dict, tuple[bytes, int] | None]:
    """What the aligner service does for one request: result dict and optional PLY."""
    from shared.mapcloud import ply_bytes

    res = align_views(pairs, p) if method == "default" else baseline(pairs, method, p)
    cloud = None
    if want_cloud and res.merged:
        pts, cols = merged_cloud(pairs, res, colour, p.voxel_m)
        cloud = (ply_bytes(pts, cols), len(pts))
    return res.to_dict(), cloud


def _closed_fit(name: str, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    if name == "affine":
        return fit_affine(X, Y)
    return kabsch(X, Y, scale=name == "similarity")


def select_model(
    X: np.ndarray, Y: np.ndarray, margin: float = 0.9, folds: int = 5, try_mlp: bool = True
):
    """Our default for correspondences: the simplest of rigid, similarity, affine and the
    thesis MLP whose cross-validated error is not beaten by `margin` x by a richer one.
    Returns (name, fitted estimator with `.transform`)."""
    from shared.estimators import AffineEstimator, RigidEstimator, SimilarityEstimator

    order = np.random.default_rng(0).permutation(len(X))

    def cv(name: str) -> float:
        errs = []
        for k in range(folds):
            test = order[k::folds]
            train = np.setdiff1d(order, test)
            M = _closed_fit(name, X[train], Y[train])
            errs.append(np.linalg.norm(apply(M, X[test]) - Y[test], axis=1))
        return float(np.mean(np.concatenate(errs)))

    best_name, best_err = "rigid", cv("rigid")
    for name in ("similarity", "affine"):
        err = cv(name)
        if err < margin * best_err:
            best_name, best_err = name, err
    scale = float(np.linalg.norm(np.ptp(Y, axis=0)))
    if try_mlp and len(X) >= 30 and best_err > 1e-9 * scale:
        # a quick trial on at most 1,000 points; the full MLP only if it clearly wins
        sub = order[:1000]
        test, train = sub[: len(sub) // 5], sub[len(sub) // 5 :]
        mlp = MLPEstimator(max_epochs=100).fit(X[train], Y[train])
        mlp_err = float(np.linalg.norm(mlp.transform(X[test]) - Y[test], axis=1).mean())
        M = _closed_fit(best_name, X[train], Y[train])
        base = float(np.linalg.norm(apply(M, X[test]) - Y[test], axis=1).mean())
        if mlp_err < margin * base:
            return "mlp", MLPEstimator().fit(X, Y)
    cls = {"rigid": RigidEstimator, "similarity": SimilarityEstimator, "affine": AffineEstimator}[
        best_name
    ]
    return best_name, cls(threshold=np.inf).fit(X, Y)
