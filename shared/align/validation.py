"""Cross-validation of a fit on correspondences: one k-fold loop for the gate's held-out
residual and for model selection."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fleetmap.estimators import MLPEstimator
from fleetmap.geometry import apply, displacement_rms, residuals
from fleetmap.registration import fit_affine, kabsch


def kfold_residuals(
    X: np.ndarray,
    Y: np.ndarray,
    fit: Callable[[np.ndarray, np.ndarray], Callable[[np.ndarray], np.ndarray]],
    folds: int = 5,
    seed: int = 0,
) -> np.ndarray:
    """Residuals (metres, shape (N,)) of each fold predicted by `fit` on the other folds;
    `fit(X, Y)` returns the fitted mapping of points."""
    order = np.random.default_rng(seed).permutation(len(X))
    res = []
    for k in range(folds):
        test = order[k::folds]
        train = np.setdiff1d(order, test)
        predict = fit(X[train], Y[train])
        res.append(np.linalg.norm(predict(X[test]) - Y[test], axis=1))
    return np.concatenate(res)


def rigid_fit(X: np.ndarray, Y: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    T = kabsch(X, Y)
    return lambda P: apply(T, P)


def affine_fit(X: np.ndarray, Y: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    T = fit_affine(X, Y)
    return lambda P: apply(T, P)


def holdout_residual(
    X: np.ndarray, Y: np.ndarray, folds: int = 5, seed: int = 0, model: str = "rigid"
) -> float:
    """Median residual of each fold predicted by a fit on the other folds (metres);
    `model`: "rigid", "affine" (closed forms) or "mlp". Fewer folds where there are fewer
    than two points a fold (each fit keeps at least four); under six points: inf."""
    if len(X) < 6:
        return float("inf")
    folds = min(folds, len(X) // 2)
    if model in ("rigid", "affine"):
        fit = rigid_fit if model == "rigid" else affine_fit
    else:

        def fit(Xt, Yt):
            return MLPEstimator(max_epochs=200, random_state=seed).fit(Xt, Yt).transform

    return float(np.median(kfold_residuals(X, Y, fit, folds, seed)))


def spread_m(points: np.ndarray) -> float:
    """Second-largest standard deviation (metres) of a point set: small for a line or a
    spot."""
    if len(points) < 3:
        return 0.0
    w = np.linalg.eigvalsh(np.cov(points.T))
    return float(np.sqrt(max(w[-2], 0.0)))


def outnumbers(n: int, m: int) -> bool:
    """Whether count n exceeds count m beyond the noise of their difference (the square
    root of their sum): how the gate compares two counts of agreeing matches."""
    return n - m > np.sqrt(n + m)


def distinct(X: np.ndarray, Y: np.ndarray, agree: np.ndarray, cell: float) -> int:
    """How many of the matches `agree` (a mask) are distinct places: a match whose points
    lie within `cell` metres of a counted one's on both sides (their six coordinates
    joined) is that one's, taken greedily, so a surface's keypoints a cell apart still
    count each (`cell` 0: every match). One point of the scene can give several keypoints
    millimetres apart (a blob's nested MSER regions, ASIFT's tilts), each with its match:
    on a HoloLens revisit 8 raw matches agreeing with an alignment 22 cm from the truth were
    four places, three of them matched two or three times (docs/ALIGNER.md, session 33)."""
    n = int(np.count_nonzero(agree))
    if cell <= 0 or n < 2:
        return n
    from scipy.spatial import cKDTree

    Z = np.hstack([X[agree], Y[agree]])
    near = cKDTree(Z).query_ball_point(Z, cell)
    taken = np.zeros(n, bool)
    kept = 0
    for k in range(n):  # greedy, so a chain of neighbours is not one place
        if not taken[k]:
            kept += 1
            taken[near[k]] = True
    return kept


def better_nearby(
    T: np.ndarray,
    X: np.ndarray,
    Y: np.ndarray,
    probe: np.ndarray,
    tol: float,
    reach: float,
    tries: int = 600,
) -> tuple[np.ndarray, int, int] | None:
    """An alignment between `tol` and `reach` (RMS over `probe`, B's points) from T that
    more matches (X -> Y) agree with, within `tol`, than agree with T, beyond the noise of
    the two counts (their difference over the square root of their sum, as
    `hypotheses.ranked`): (T_near, its count, T's count), or None.

    Where the matches pin the alignment, none is found: right merges of the recall bench
    (SUN3D, HoloLens, TUM desk) had none further than 5 cm. Where only the maps' geometry
    led there (surfaces that slide along each other), the matches prefer a place nearby:
    SUN3D windows merged 10-15 cm from the truth had 77-124 matches agreeing with an
    alignment 15-35 cm away against 31-73 for the merge (docs/ALIGNER.md)."""
    r = residuals(T, X, Y)
    n_T = int(np.count_nonzero(r < tol))
    near = np.flatnonzero(r < reach + tol)
    if len(near) < 3:
        return None
    rng = np.random.default_rng(0)
    Xn, Yn = X[near], Y[near]
    sub = rng.permutation(len(near))[:1500]  # counted on at most 1,500 of them
    Xs, Ys = Xn[sub], Yn[sub]
    best_n, best_T = -1, None
    for _ in range(tries):
        i = rng.choice(len(near), 3, replace=False)
        if np.linalg.norm(np.cross(Xn[i[1]] - Xn[i[0]], Xn[i[2]] - Xn[i[0]])) < 1e-4:
            continue  # collinear: no rotation
        Tc = kabsch(Xn[i], Yn[i])
        if displacement_rms(Tc, T, probe) > reach:
            continue
        n = int(np.count_nonzero(residuals(Tc, Xs, Ys) < tol))
        if n > best_n:
            best_n, best_T = n, Tc
    if best_T is None:
        return None
    agree = residuals(best_T, Xn, Yn) < tol
    refit = kabsch(Xn[agree], Yn[agree]) if agree.sum() >= 3 else best_T
    if displacement_rms(refit, T, probe) <= reach:
        best_T = refit
    n = int(np.count_nonzero(residuals(best_T, X, Y) < tol))
    if displacement_rms(best_T, T, probe) <= tol or not outnumbers(n, n_T):
        return None
    return best_T, n, n_T
