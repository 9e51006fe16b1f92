"""Closed-form rigid fits (Kabsch/Umeyama) and a vectorised RANSAC over 3D-3D matches."""

from __future__ import annotations

import numpy as np

from fleetmap.errors import BadInput, NotEnoughCorrespondences


def kabsch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, scale: bool = False
) -> np.ndarray:
    """Least-squares T (4x4) with dst ~ T(src): rigid, or similarity with `scale`.

    src, dst : ndarray of shape (N, 3), N >= 3, not all collinear.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise BadInput(f"Expected two point sets of shape (N, 3), got {src.shape}, {dst.shape}")
    if len(src) < 3:
        raise NotEnoughCorrespondences(f"A rigid fit needs 3 correspondences, got {len(src)}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    cs, cd = src - mu_s, dst - mu_d
    H = (cs * w[:, None]).T @ cd
    U, S, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    s = float(np.trace(np.diag(S) @ D) / (w @ (cs**2).sum(1))) if scale else 1.0
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = mu_d - s * R @ mu_s
    return T


def _batch_kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid fits of shape (H, 3, 3) and (H, 3) for H minimal samples of shape (H, 3, 3)."""
    mu_s, mu_d = src.mean(1), dst.mean(1)
    H = np.einsum("hni,hnj->hij", src - mu_s[:, None], dst - mu_d[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))
    d[d == 0] = 1.0
    Vt[:, 2, :] *= d[:, None]
    R = np.einsum("hji,hkj->hik", Vt, U)
    t = mu_d - np.einsum("hij,hj->hi", R, mu_s)
    return R, t


def ransac_rigid(
    src: np.ndarray,
    dst: np.ndarray,
    tol: float,
    iterations: int = 1000,
    seed: int = 0,
    min_spread: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC over 3-point rigid fits, then a least-squares refit on the inliers.

    src, dst : ndarray of shape (N, 3), matched points. tol : inlier distance.
    Returns (T of shape (4, 4) mapping src into dst, inlier mask of shape (N,)).
    Raises NotEnoughCorrespondences with fewer than 3 matches.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if n < 3:
        raise NotEnoughCorrespondences(f"RANSAC needs 3 correspondences, got {n}")
    rng = np.random.default_rng(seed)
    if n <= 22:  # every triplet: at most 1540
        idx = np.array(np.triu_indices(n, 1)).T
        trip = np.array([(i, j, k) for i, j in idx for k in range(j + 1, n)])
    else:
        trip = np.stack([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    s, d = src[trip], dst[trip]
    # degenerate samples: nearly collinear or inconsistent pairwise distances
    ds = np.linalg.norm(s[:, [0, 1, 2]] - s[:, [1, 2, 0]], axis=2)
    dd = np.linalg.norm(d[:, [0, 1, 2]] - d[:, [1, 2, 0]], axis=2)
    area = np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1)
    ok = (np.abs(ds - dd).max(1) < 2 * tol) & (area > min_spread)
    best = np.zeros(n, bool)
    if ok.any():
        R, t = _batch_kabsch(s[ok], d[ok])
        for lo in range(0, len(R), 256):  # bound memory: 256 hypotheses x N points
            pred = np.einsum("hij,nj->hni", R[lo : lo + 256], src) + t[lo : lo + 256, None]
            inl = ((pred - dst[None]) ** 2).sum(2) < tol * tol
            k = inl.sum(1).argmax()
            if inl[k].sum() > best.sum():
                best = inl[k]
            # adaptive stop: enough samples for a 99.9% chance of one all-inlier triplet
            w = best.sum() / n
            if w > 0 and lo + 256 >= np.log(1e-3) / np.log(max(1 - w**3, 1e-12)):
                break
    if best.sum() < 3:
        return np.eye(4), np.zeros(n, bool)
    T = kabsch(src[best], dst[best])
    inl = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < tol
    if inl.sum() >= best.sum():
        best = inl
        T = kabsch(src[best], dst[best])
    return T, best
