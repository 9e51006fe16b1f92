"""Thesis Tables 3.2-3.5 on the Laurana bust, and our estimators beside the thesis MLP.

    .venv/bin/python bench/alignment.py [--repeats 3] [--quick]

Protocol (thesis 3.5): the 27,861 vertices are split along the bust's x axis into view P
(first 15,000) and view Q (last 17,861), overlapping in L (5,000 points, 30%). Q is
moved by T1-T4 exactly as printed in Table 3.2 (d = A q + tr). Estimators learn P -> D from
pairs (l, T l), l in L, with Gaussian noise of sigma units on both sides of the training
pairs. Each cell is the mean over repeats (different samples and noise) of the mean point
error, measured three ways, since the thesis does not say which: on the training
correspondences (noise-free truth), on held-out overlap points, and on the whole second
view (every q in Q: what a merged map needs, the MLP extrapolating beyond the overlap).
Columns: ICP from identity (Open3D, point-to-point, between P and D), the thesis MLP
(3-20-3, scaled tanh, Levenberg-Marquardt), closed-form rigid / similarity / affine
(least squares), and our default for correspondences (`select_model`: cross-validated
choice among those, the MLP only where it lowers the held-out error).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from fleetmap.align import select_model
from fleetmap.estimators import MLPEstimator
from fleetmap.registration import fit_affine, kabsch

ROOT = Path(__file__).resolve().parents[1]
PLY = ROOT.parent / "shared/data/laurana/Laurana50k.ply"
T = {
    "T1": [
        [0.9997, -0.0174, -0.0175, 100],
        [0.0171, 0.9997, -0.0174, 300],
        [0.0178, 0.0171, 0.9997, 70],
    ],
    "T2": [[0.36, 0.48, -0.8, 100], [-0.8, 0.6, 0, 300], [0.48, 0.64, 0.6, 70]],
    "T3": [[1, 0.5, 0, 100], [0, 0.7071, 0.7071, 300], [0, -0.7071, 0.1072, 70]],
    "T4": [[0.36, 0.48, 0, 100], [0, 0.6, 0, 300], [0.48, 0.64, 0.6, 70]],
}
THESIS_32 = {
    "T1": (7.67e-4, 0.0059),
    "T2": (2.42e-12, 0.3381),
    "T3": (30.5096, 0.0427),
    "T4": (103.54, 0.0029),
}
THESIS_33 = {
    0.5: (5.5, 2.01, 1.42, 7.86),
    1: (12.45, 13.39, 11.65, 27.53),
    2: (17.57, 27.29, 12.38, 36.42),
}


def load_views():
    p = np.asarray(o3d.io.read_point_cloud(str(PLY)).points, np.float64)
    order = np.argsort(p[:, 0], kind="stable")
    P, Q, L = p[order[:15000]], p[order[10000:]], p[order[10000:15000]]
    return P, Q, L


def _apply(M, X):
    M = np.asarray(M, np.float64)
    return X @ M[:3, :3].T + M[:3, 3]


def fps(X: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Farthest-point sampling: n indices spread over X."""
    rng = np.random.default_rng(seed)
    idx = [int(rng.integers(len(X)))]
    d = np.linalg.norm(X - X[idx[0]], axis=1)
    for _ in range(n - 1):
        idx.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(X - X[idx[-1]], axis=1))
    return np.array(idx)


def fit(method: str, X, Y, P=None, D=None):
    """A callable mapping P-frame points to D-frame points, and the fit time."""
    t = time.perf_counter()
    if method == "icp":
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(D))
        dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        reg = o3d.pipelines.registration
        r = reg.registration_icp(
            src,
            dst,
            20.0,
            np.eye(4),
            reg.TransformationEstimationPointToPoint(),
            reg.ICPConvergenceCriteria(max_iteration=200),
        )
        M = np.linalg.inv(r.transformation)
        f = lambda Z: _apply(M, Z)  # noqa: E731
    elif method == "mlp":
        est = MLPEstimator().fit(X, Y)
        f = est.transform
    elif method in ("rigid", "similarity"):
        M = kabsch(X, Y, scale=method == "similarity")
        f = lambda Z: _apply(M, Z)  # noqa: E731
    elif method == "affine":
        M = fit_affine(X, Y)
        f = lambda Z: _apply(M, Z)  # noqa: E731
    else:
        name, est = select_model(X, Y)
        f = est.transform
    return f, time.perf_counter() - t


METHODS = ["icp", "mlp", "rigid", "similarity", "affine", "default"]


def cell(Tk, method, n_train, sigma, spread, repeats, views):
    P, Q, L = views
    M = np.vstack([np.array(T[Tk]), [0, 0, 0, 1]])
    D = _apply(M, Q)
    out = []
    for r in range(repeats):
        rng = np.random.default_rng(1000 * r + int(sigma * 10) + n_train)
        idx = fps(L, n_train, r) if spread else rng.choice(len(L), n_train, replace=False)
        held = np.setdiff1d(np.arange(len(L)), idx)
        X, Ytrue = L[idx], _apply(M, L[idx])
        Xn = X + rng.normal(0, sigma, X.shape)
        Yn = Ytrue + rng.normal(0, sigma, X.shape)
        f, secs = fit(method, Xn, Yn, P, D)
        e_train = np.linalg.norm(f(X) - Ytrue, axis=1).mean()
        e_held = (
            np.linalg.norm(f(L[held]) - _apply(M, L[held]), axis=1).mean() if len(held) else np.nan
        )
        e_view = np.linalg.norm(f(Q) - D, axis=1).mean()
        out.append((e_train, e_held, e_view, secs))
    return np.mean(out, axis=0)


def fmt(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x:.2e}" if (x < 0.01 and x != 0) or x >= 1000 else f"{x:.4f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="Table 3.2 only")
    args = ap.parse_args()
    views = load_views()
    print(f"P {len(views[0])}, Q {len(views[1])}, overlap L {len(views[2])} points\n")

    print(
        "Table 3.2, noise 0, 4,000 training pairs (random in L), 1,000 held out; "
        "mean error train / held-out / whole second view (units), fit time"
    )
    print("| T | thesis ICP | thesis NN | " + " | ".join(METHODS) + " |")
    print("|---|---|---|" + "---|" * len(METHODS))
    for Tk in T:
        cells = [cell(Tk, m, 4000, 0.0, False, args.repeats, views) for m in METHODS]
        row = [f"{fmt(c[0])} / {fmt(c[1])} / {fmt(c[2])} ({c[3]:.2f} s)" for c in cells]
        print(
            f"| {Tk} | {fmt(THESIS_32[Tk][0])} | {fmt(THESIS_32[Tk][1])} | "
            + " | ".join(row)
            + " |"
        )
    if args.quick:
        return

    print(
        "\nTable 3.3, noise sigma (units), 4,000 training pairs; whole second view "
        "(held-out overlap in brackets)"
    )
    print("| sigma | T | thesis NN | " + " | ".join(METHODS[1:]) + " |")
    print("|---|---|---|" + "---|" * (len(METHODS) - 1))
    for sigma in (0.5, 1.0, 2.0):
        for k, Tk in enumerate(T):
            cells = [cell(Tk, m, 4000, sigma, False, args.repeats, views) for m in METHODS[1:]]
            row = [f"{fmt(c[2])} ({fmt(c[1])})" for c in cells]
            print(f"| {sigma} | {Tk} | {THESIS_33[sigma][k]} | " + " | ".join(row) + " |")

    print(
        "\nTables 3.4 / 3.5, thesis MLP vs rigid, noise 0: training size, random vs spread "
        "(farthest-point) selection; whole second view (held-out overlap)"
    )
    print("| T | n | MLP random | MLP spread | rigid random | rigid spread |")
    print("|---|---|---|---|---|---|")
    for Tk in ("T1", "T2"):
        for n in (100, 400, 1000, 2000, 4000):
            cs = [
                cell(Tk, m, n, 0.0, s, args.repeats, views)
                for m in ("mlp", "rigid")
                for s in (False, True)
            ]
            print(f"| {Tk} | {n} | " + " | ".join(f"{fmt(c[2])} ({fmt(c[1])})" for c in cs) + " |")


if __name__ == "__main__":
    main()
