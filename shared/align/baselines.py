"""Alignments to compare the default with (`BASELINES`, registered in
`fleetmap.align.methods`): one estimator alone on the visual correspondences, ICP from
identity, the map_merge_3d recipe (FPFH + RANSAC + ICP); and `select_model`, the
cross-validated choice among closed forms and the MLP."""

from __future__ import annotations

import time

import numpy as np

from fleetmap.align.types import AlignParams, AlignResult, unique_views
from fleetmap.align.validation import kfold_residuals
from fleetmap.correspondences import pooled_correspondences
from fleetmap.estimators import MLPEstimator
from fleetmap.geometry import apply
from fleetmap.mapcloud import REG, SEEDED, icp, views_cloud
from fleetmap.registration import MODELS


def _closed_form(name: str):
    def run(pairs, p: AlignParams) -> AlignResult:
        from fleetmap.estimators import AffineEstimator, RigidEstimator, SimilarityEstimator

        kinds = {"rigid": RigidEstimator, "similarity": SimilarityEstimator}
        cls = kinds.get(name, AffineEstimator)
        t0, C = time.perf_counter(), pooled_correspondences(pairs)
        e = cls(threshold=p.ransac_tol_m).fit(C.X, C.Y)
        return AlignResult(
            True, f"{name} in RANSAC (no gate)", e.T_, name, len(C), int(e.inliers_.sum()),
            seconds=time.perf_counter() - t0,
        )  # fmt: skip

    return run


def mlp_alone(pairs, p: AlignParams) -> AlignResult:
    """The thesis MLP on the pooled visual correspondences, no gate."""
    t0, C = time.perf_counter(), pooled_correspondences(pairs)
    m = MLPEstimator().fit(C.X, C.Y)
    return AlignResult(
        True, "thesis MLP (no gate)", m.affine_, "mlp", len(C), len(C), mlp=m,
        seconds=time.perf_counter() - t0,
    )  # fmt: skip


def icp_from_identity(pairs, p: AlignParams) -> AlignResult:
    """ICP from identity on the two robots' map clouds (the thesis's ICP baseline)."""
    t0 = time.perf_counter()
    ca = views_cloud(unique_views(pairs, 0), voxel=p.voxel_m)
    cb = views_cloud(unique_views(pairs, 1), voxel=p.voxel_m)
    T, fit, _ = icp(cb, ca, np.eye(4))
    return AlignResult(
        True, "ICP from identity (no gate)", T, "icp", fitness=fit,
        seconds=time.perf_counter() - t0,
    )  # fmt: skip


def recipe(pairs, p: AlignParams) -> AlignResult:
    """The map_merge_3d recipe on the depth clouds (`fpfh_ransac_icp`), no gate."""
    t0 = time.perf_counter()
    T, fit = fpfh_ransac_icp(unique_views(pairs, 0), unique_views(pairs, 1))
    return AlignResult(
        True, "FPFH + RANSAC + point-to-plane ICP on the depth clouds (no gate)", T, "fpfh",
        fitness=fit, seconds=time.perf_counter() - t0,
    )  # fmt: skip


#: the baselines of `fleetmap.align.methods.METHODS`, by name
BASELINES = {
    "rigid": _closed_form("rigid"),
    "similarity": _closed_form("similarity"),
    "affine": _closed_form("affine"),
    "mlp": mlp_alone,
    "icp": icp_from_identity,
    "fpfh": recipe,
}


def fpfh_ransac_icp(views_a, views_b, voxel: float = 0.05, seed: int = 0):
    """The purely geometric recipe of the ROS map_merge_3d tool, with Open3D: fused depth
    clouds, FPFH features, feature-matching RANSAC, point-to-plane ICP. No images used.
    Returns (T_a_b, overlap fitness)."""
    import open3d as o3d

    ca, cb = views_cloud(views_a, voxel=voxel), views_cloud(views_b, voxel=voxel)
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    fa, fb = REG.compute_fpfh_feature(ca, param), REG.compute_fpfh_feature(cb, param)
    with SEEDED:
        o3d.utility.random.seed(seed)
        r = REG.registration_ransac_based_on_feature_matching(
            cb,
            ca,
            fb,
            fa,
            True,
            1.5 * voxel,
            REG.TransformationEstimationPointToPoint(False),
            3,
            [
                REG.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                REG.CorrespondenceCheckerBasedOnDistance(1.5 * voxel),
            ],
            REG.RANSACConvergenceCriteria(100_000, 0.999),
        )
    T, fit, _ = icp(cb, ca, r.transformation, distances=(2 * voxel, voxel, 0.6 * voxel))
    return T, fit


def _closed_fit(name: str, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    return MODELS[name][1](X, Y)


def select_model(
    X: np.ndarray, Y: np.ndarray, margin: float = 0.9, folds: int = 5, try_mlp: bool = True
):
    """Our default for correspondences: the simplest of rigid, similarity, affine and the
    thesis MLP whose cross-validated error is not beaten by `margin` x by a richer one.
    Returns (name, fitted estimator with `.transform`)."""
    from fleetmap.estimators import AffineEstimator, RigidEstimator, SimilarityEstimator

    order = np.random.default_rng(0).permutation(len(X))

    def cv(name: str) -> float:
        def fit(Xt, Yt):
            M = _closed_fit(name, Xt, Yt)
            return lambda P: apply(M, P)

        return float(np.mean(kfold_residuals(X, Y, fit, folds, seed=0)))

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
