"""Transform estimators between two robots' map frames, scikit-learn style.

`fit(X, Y)` learns Y ~ f(X) from matched 3D points (X in robot B's map frame, Y in robot
A's) and returns self; `transform(X)` maps points; fitted attributes end in `_`.

- `RigidEstimator`, `SimilarityEstimator`, `AffineEstimator`: closed form inside RANSAC,
  so wrong correspondences are rejected (`inliers_`).
- `MLPEstimator`: the thesis's network (Chapter 3): 3 inputs, one hidden layer of scaled
  tanh 1.7159 tanh(2/3 v), 3 linear outputs, inputs and targets normalised (centring,
  decorrelation, covariance equalisation), full-batch Levenberg-Marquardt training with
  Matlab trainlm's stopping rules (error goal, max epochs, 6 validation failures).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from fleetmap.errors import BadInput, NotEnoughCorrespondences
from fleetmap.registration import MODELS, fit_affine, ransac

log = logging.getLogger(__name__)


def _check_xy(X: np.ndarray, Y: np.ndarray, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    X, Y = np.asarray(X, np.float64), np.asarray(Y, np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape != Y.shape:
        raise BadInput(f"Expected X and Y of shape (N, 3), got {X.shape} and {Y.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        raise BadInput("Correspondences have non-finite values")
    if len(X) < minimum:
        raise NotEnoughCorrespondences(f"Need at least {minimum} correspondences, got {len(X)}")
    if (
        np.linalg.matrix_rank(X - X.mean(0), tol=1e-9 * max(1.0, np.abs(X).max())) < 3
        and minimum >= 4
    ):
        raise BadInput("Degenerate correspondences: the points are coplanar or collinear")
    return X, Y


class _ClosedForm:
    """Closed-form model in RANSAC: minimal samples, inliers by distance, LS refit."""

    sample_size = 3
    min_points = 3

    def __init__(
        self, threshold: float | None = None, max_trials: int = 2000, random_state: int = 0
    ):
        self.threshold = threshold
        self.max_trials = max_trials
        self.random_state = random_state

    def _fit(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        return MODELS[self.model][1](X, Y)

    def fit(self, X: np.ndarray, Y: np.ndarray):
        X, Y = _check_xy(X, Y, self.min_points)
        t0 = time.perf_counter()
        thr = self.threshold
        if thr is None:  # robust default: from the spread of a first all-points fit
            r = np.linalg.norm(self._apply(self._fit(X, Y), X) - Y, axis=1)
            thr = max(3.0 * 1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-9)
        T, best = ransac(X, Y, thr, self.model, self.max_trials, self.random_state)
        if best.sum() < self.min_points:
            raise NotEnoughCorrespondences(f"RANSAC found {int(best.sum())} inliers")
        self.T_, self.inliers_, self.threshold_ = T, best, thr
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    @staticmethod
    def _apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
        return X @ T[:3, :3].T + T[:3, 3]

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Map points of shape (N, 3) from B's frame into A's."""
        return self._apply(self.T_, np.asarray(X, np.float64))

    predict = transform

    @property
    def affine_(self) -> np.ndarray:
        return self.T_


class RigidEstimator(_ClosedForm):
    """Rotation and translation (Kabsch) in RANSAC."""

    model = "rigid"


class SimilarityEstimator(_ClosedForm):
    """Rotation, translation and one scale (Umeyama) in RANSAC."""

    model = "similarity"


class AffineEstimator(_ClosedForm):
    """General affine map (least squares) in RANSAC."""

    model = "affine"
    sample_size = 4
    min_points = 4


class _Whitener:
    """Centring, decorrelation (PCA) and covariance equalisation (LeCun's recipe)."""

    def fit(self, X: np.ndarray) -> _Whitener:
        self.mean_ = X.mean(0)
        C = np.cov((X - self.mean_).T) + 1e-12 * np.eye(X.shape[1])
        w, V = np.linalg.eigh(C)
        w = np.maximum(w, 1e-12 * w.max())
        self.W_ = V / np.sqrt(w)  # columns scaled: unit variance along each axis
        self.Winv_ = (V * np.sqrt(w)).T
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        return (X - self.mean_) @ self.W_

    def inverse(self, Z: np.ndarray) -> np.ndarray:
        return Z @ self.Winv_ + self.mean_


class MLPEstimator:
    """The thesis's MLP: 3 -> hidden (scaled tanh) -> 3 linear, trained by LM.

    Parameters
    ----------
    hidden : hidden units (thesis: 20).
    max_epochs, goal, max_fail, min_grad, mu : Matlab trainlm's stopping rules and
        damping (defaults 1000, 0, 6, 1e-7, 1e-3).
    val_fraction : held-out share for the validation-failure rule.
    optimizer : "lm" (Levenberg-Marquardt) or "adam" (first order, for comparison).
    init : "linear" (default): first-layer weights LeCun-random times 0.1, so the hidden
        units start in tanh's linear range, and the output layer solved by least squares
        on them: training starts from about the best affine map and LM fits what remains.
        "lecun": both layers random (Matlab's style of start). Measured on the Laurana
        overlap (4,000 pairs, 1,000 epochs, held-out error): T1 3.3e-5 against 6.1e-4,
        T4 2.7e-5 against 7.7e-4 (docs/BENCHMARKS.md).
    """

    A, B = 1.7159, 2.0 / 3.0

    def __init__(
        self,
        hidden: int = 20,
        max_epochs: int = 1000,
        goal: float = 0.0,
        max_fail: int = 6,
        min_grad: float = 1e-7,
        mu: float = 1e-3,
        val_fraction: float = 0.15,
        optimizer: str = "lm",
        random_state: int = 0,
        init: str = "linear",
    ):
        self.hidden, self.max_epochs, self.goal = hidden, max_epochs, goal
        self.max_fail, self.min_grad, self.mu = max_fail, min_grad, mu
        self.val_fraction, self.optimizer, self.random_state = val_fraction, optimizer, random_state
        self.init = init

    def _forward(self, theta, Z, xp=np):
        """The network's outputs for whitened inputs Z (N, 3); `xp`: numpy, or torch for
        the Adam comparison's autograd."""
        h = self.hidden
        W1 = theta[: 3 * h].reshape(h, 3)
        b1 = theta[3 * h : 4 * h]
        W2 = theta[4 * h : 7 * h].reshape(3, h)
        b2 = theta[7 * h : 7 * h + 3]
        return (self.A * xp.tanh(self.B * (Z @ W1.T + b1))) @ W2.T + b2

    def _normal_equations(self, theta: np.ndarray, Z: np.ndarray, e: np.ndarray):
        """J^T J (P, P) and J^T e (P,) without forming J, from its block structure.

        Output k depends on the second layer only through row k of W2 and b2, and on the
        first layer through W2[k] * tanh'. With F = tanh' (x) [z, 1] (N, 4h) and
        A = [a, 1] (N, h+1): the first-layer block is (F^T F) * kron(W2^T W2, 1), the
        cross blocks W2[k] * (F^T A), the second-layer blocks A^T A (the same for every k).
        About 7x fewer operations than J^T J over the (3N, P) Jacobian."""
        h, n = self.hidden, len(Z)
        W1 = theta[: 3 * h].reshape(h, 3)
        b1 = theta[3 * h : 4 * h]
        W2 = theta[4 * h : 7 * h].reshape(3, h)
        t = np.tanh(self.B * (Z @ W1.T + b1))
        da = self.A * self.B * (1 - t * t)  # (N, h)
        one = np.ones((n, 1))
        Zt = np.hstack([Z, one])  # (N, 4)
        At = np.hstack([self.A * t, one])  # (N, h+1)
        F = (da[:, :, None] * Zt[:, None, :]).reshape(n, 4 * h)
        Q = F.T @ F
        M = np.kron(W2.T @ W2, np.ones((4, 4)))
        B = F.T @ At  # (4h, h+1)
        AA = At.T @ At
        m = h + 1
        size = 4 * h + 3 * m
        H = np.zeros((size, size))
        H[: 4 * h, : 4 * h] = Q * M
        w = np.repeat(W2, 4, axis=1)  # (3, 4h): W2[k, j] at (j, q)
        g = np.empty(size)
        eW = e @ W2  # (N, h)
        g[: 4 * h] = ((eW * da).T @ Zt).reshape(-1)
        for k in range(3):
            lo = 4 * h + k * m
            blk = w[k][:, None] * B
            H[: 4 * h, lo : lo + m] = blk
            H[lo : lo + m, : 4 * h] = blk.T
            H[lo : lo + m, lo : lo + m] = AA
            g[lo : lo + m] = At.T @ e[:, k]
        inv = self._layout()
        return H[np.ix_(inv, inv)], g[inv]

    def _layout(self) -> np.ndarray:
        """For each index of theta, its index in the augmented layout used above."""
        if getattr(self, "_inv", None) is None or len(self._inv) != 7 * self.hidden + 3:
            h = self.hidden
            idx = []
            for j in range(h):
                idx += [j * 3, j * 3 + 1, j * 3 + 2, 3 * h + j]
            for k in range(3):
                idx += [4 * h + k * h + r for r in range(h)] + [7 * h + k]
            self._inv = np.argsort(idx)
        return self._inv

    def _init(self, rng: np.random.Generator) -> np.ndarray:
        h = self.hidden
        # LeCun initialisation: weights ~ N(0, 1/fan_in)
        W1 = rng.standard_normal((h, 3)) / np.sqrt(3)
        W2 = rng.standard_normal((3, h)) / np.sqrt(h)
        return np.concatenate([W1.ravel(), np.zeros(h), W2.ravel(), np.zeros(3)])

    def _linear_start(self, theta: np.ndarray, Zx: np.ndarray, Zy: np.ndarray) -> np.ndarray:
        h = self.hidden
        W1 = theta[: 3 * h].reshape(h, 3) * 0.1
        H = self.A * np.tanh(self.B * (Zx @ W1.T))
        Ha = np.hstack([H, np.ones((len(H), 1))])
        sol = np.linalg.lstsq(Ha, Zy, rcond=None)[0]  # (h + 1, 3), LAPACK's gelsd
        return np.concatenate([W1.ravel(), np.zeros(h), sol[:h].T.ravel(), sol[h]])

    def fit(self, X: np.ndarray, Y: np.ndarray) -> MLPEstimator:
        """Train on X (N, 3) -> Y (N, 3). numpy throughout (torch only for the Adam
        comparison): a network of ~150 weights needs no tensor library, and importing torch
        was 1.8 s of a SUN3D merge's 1.9 s MLP try (py-spy, session 31)."""
        from threadpoolctl import threadpool_limits

        X, Y = _check_xy(X, Y, 10)
        t0 = time.perf_counter()
        self.x_norm_ = _Whitener().fit(X)
        self.y_norm_ = _Whitener().fit(Y)
        Zx, Zy = self.x_norm_.transform(X), self.y_norm_.transform(Y)
        rng = np.random.default_rng(self.random_state)
        perm = rng.permutation(len(X))
        n_val = int(round(self.val_fraction * len(X))) if len(X) >= 20 else 0
        val, tr = perm[:n_val], perm[n_val:]
        theta = self._init(np.random.default_rng([self.random_state, 1]))
        if self.init == "linear":
            theta = self._linear_start(theta, Zx[tr], Zy[tr])
        elif self.init != "lecun":
            raise BadInput(f"Unknown init {self.init!r} (linear or lecun)")
        train = self._train_lm if self.optimizer == "lm" else self._train_adam
        # ~150 weights: the products are small (at most 5,000 x 80), and one thread beats
        # two here (measured: 2 ms against 15 ms per product when the other core is busy)
        with threadpool_limits(1):
            theta, self.n_epochs_, self.stop_reason_ = train(
                theta, Zx[tr], Zy[tr], Zx[val], Zy[val]
            )
        self.theta_ = theta
        self.fit_seconds_ = time.perf_counter() - t0
        self.affine_ = fit_affine(X, self.transform(X))
        return self

    def _mse(self, theta, Zx, Zy) -> float:
        return float(((self._forward(theta, Zx) - Zy) ** 2).mean()) if len(Zx) else 0.0

    def _train_lm(self, theta, Zx, Zy, Vx, Vy):
        mu, best_val, fails = self.mu, np.inf, 0
        best_theta = theta.copy()
        eye = np.eye(len(theta))

        def residual(t):
            return (self._forward(t, Zx) - Zy).reshape(-1)

        e = residual(theta)  # kept from the accepted step: one forward pass per epoch
        for epoch in range(1, self.max_epochs + 1):
            sse = float(e @ e)
            if sse / len(e) <= self.goal:
                return theta, epoch, "goal"
            JtJ, g = self._normal_equations(theta, Zx, e.reshape(-1, 3))
            if float(np.abs(g).max()) < self.min_grad:
                return theta, epoch, "min_grad"
            while True:
                step = np.linalg.solve(JtJ + mu * eye, g)
                cand = theta - step
                e2 = residual(cand)
                if float(e2 @ e2) < sse:
                    theta, mu, e = cand, max(mu * 0.1, 1e-20), e2
                    break
                mu *= 10.0
                if mu > 1e10:
                    return theta, epoch, "max_mu"
            if len(Vx):
                v = self._mse(theta, Vx, Vy)
                if v < best_val:
                    best_val, best_theta, fails = v, theta.copy(), 0
                else:
                    fails += 1
                    if fails >= self.max_fail:
                        return best_theta, epoch, "validation"
        return theta, self.max_epochs, "max_epochs"

    def _train_adam(self, theta, Zx, Zy, Vx, Vy):
        import torch  # the first-order comparison's autograd

        Zx, Zy = torch.from_numpy(Zx), torch.from_numpy(Zy)
        theta = torch.from_numpy(theta).requires_grad_(True)
        opt = torch.optim.Adam([theta], lr=1e-2)
        best_val, best_theta, fails = np.inf, theta.detach().numpy().copy(), 0
        for epoch in range(1, self.max_epochs + 1):
            opt.zero_grad()
            loss = ((self._forward(theta, Zx, torch) - Zy) ** 2).mean()
            loss.backward()
            opt.step()
            if len(Vx) and epoch % 10 == 0:
                v = self._mse(theta.detach().numpy(), Vx, Vy)
                if v < best_val:
                    best_val, best_theta, fails = v, theta.detach().numpy().copy(), 0
                else:
                    fails += 1
                    if fails >= self.max_fail:
                        return best_theta, epoch, "validation"
        return theta.detach().numpy().copy(), self.max_epochs, "max_epochs"

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Map points of shape (N, 3) from B's frame into A's."""
        Z = self.x_norm_.transform(np.asarray(X, np.float64))
        return self.y_norm_.inverse(self._forward(self.theta_, Z))

    predict = transform
