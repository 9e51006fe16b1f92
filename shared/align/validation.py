"""Cross-validation of a fit on correspondences: one k-fold loop for the gate's held-out
residual and for model selection."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fleetmap.estimators import MLPEstimator
from fleetmap.geometry import apply
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


def spread(points: np.ndarray) -> float:
    """Second-largest standard deviation of a point set: small for a line or a spot."""
    if len(points) < 3:
        return 0.0
    w = np.linalg.eigvalsh(np.cov(points.T))
    return float(np.sqrt(max(w[-2], 0.0)))
