"""Closed-form rigid fits (Kabsch/Umeyama) and a vectorised RANSAC over 3D-3D matches."""

from __future__ import annotations

import numpy as np

from fleetmap.errors import BadInput, NotEnoughCorrespondences
from fleetmap.geometry import residuals


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


def fit_affine(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Least-squares affine 4x4 with Y ~ A X + t."""
    Xh = np.hstack([X, np.ones((len(X), 1))])
    M, *_ = np.linalg.lstsq(Xh, Y, rcond=None)
    T = np.eye(4)
    T[:3, :] = M.T
    return T


#: The closed forms RANSAC fits: model name -> (minimal sample size, least-squares fit).
MODELS = {
    "rigid": (3, kabsch),
    "similarity": (3, lambda X, Y: kabsch(X, Y, scale=True)),
    "affine": (4, fit_affine),
}


def _batch_kabsch(
    src: np.ndarray, dst: np.ndarray, scale: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (or similarity) fits of shape (H, 3, 3) and (H, 3) for H minimal samples of
    shape (H, k, 3)."""
    mu_s, mu_d = src.mean(1), dst.mean(1)
    cs = src - mu_s[:, None]
    H = np.einsum("hni,hnj->hij", cs, dst - mu_d[:, None])
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))
    d[d == 0] = 1.0
    Vt[:, 2, :] *= d[:, None]
    R = np.einsum("hji,hkj->hik", Vt, U)
    if scale:  # Umeyama: trace(S D) / variance of the source
        var = np.maximum((cs**2).sum((1, 2)), 1e-300)
        R = R * ((S[:, 0] + S[:, 1] + d * S[:, 2]) / var)[:, None, None]
    t = mu_d - np.einsum("hij,hj->hi", R, mu_s)
    return R, t


def _minimal_fits(s: np.ndarray, d: np.ndarray, model: str) -> tuple[np.ndarray, np.ndarray]:
    """Linear parts (H, 3, 3) and translations (H, 3) of the minimal samples' fits."""
    if model != "affine":
        return _batch_kabsch(s, d, scale=model == "similarity")
    A = np.concatenate([s, np.ones(s.shape[:2] + (1,))], 2)  # (H, 4, 4)
    sol = np.linalg.solve(A, d)  # (H, 4, 3): rows M^T then t
    return np.transpose(sol[:, :3, :], (0, 2, 1)), sol[:, 3, :]


def _usable_blocks(src, dst, k: int, iterations: int, rng, tol, model, min_spread):
    """The usable minimal samples (`_usable`) of `iterations` random ones (every triplet
    where there are at most 22 matches), in the order drawn, in blocks of 256 (the last
    shorter): drawn as the blocks are taken, so a RANSAC that stops early does not draw
    the rest. Each draw is `rng.choice(n, k, replace=False)`'s (`_choices`: 64 at a time):
    drawing all 2,000 up front was 6% of a simulated fleet's merge (py-spy, session 23),
    mostly for samples the adaptive stop never looked at."""
    n = len(src)
    if k == 3 and n <= 22:  # every triplet: at most 1540
        idx = np.array(np.triu_indices(n, 1)).T
        chunks = iter([np.array([(i, j, m) for i, j in idx for m in range(j + 1, n)])])
    else:
        chunks = (_choices(rng, n, k, min(64, iterations - lo)) for lo in range(0, iterations, 64))
    kept, have = [], 0
    for trip in chunks:
        ok = _usable(src[trip], dst[trip], tol, model, min_spread)
        kept.append(trip[ok])
        have += int(ok.sum())
        while have >= 256:
            block = np.concatenate(kept)
            yield block[:256]
            kept, have = [block[256:]], have - 256
    if have:
        yield np.concatenate(kept)


def _choices(rng: np.random.Generator, n: int, k: int, count: int) -> np.ndarray:
    """`count` draws of `rng.choice(n, k, replace=False)`, (count, k), the same values and
    `rng` left in the same state, from one block of the bit generator's words.

    numpy 2's Generator draws k of n (n <= 10,000 or k <= n // 50) by Floyd's algorithm, then
    shuffles them: k + k - 1 bounded integers per draw, each Lemire's product of one 32-bit
    word (two per PCG64 output, low half first), drawn again only where the product's low
    half falls under (2^32 - 1 - bound) mod (bound + 1). Done here for all draws at once;
    where a word would be drawn again (about bound / 2^32 per word), where n = k (a bound of
    0 draws nothing), a k numpy draws otherwise (a tail shuffle), or another bit generator,
    `rng.choice` itself. One call per sample was half of RANSAC's time: 14 -> 1.4 ms for
    2,000 samples (session 24); the unit tests hold it to `rng.choice`, value for value."""
    bg = rng.bit_generator
    state = bg.state
    floyd = n <= 10_000 or k <= n // 50
    if state.get("bit_generator") != "PCG64" or not k < n < 2**31 or not floyd:
        return np.stack([rng.choice(n, k, replace=False) for _ in range(count)])
    bounds = np.array([*range(n - k, n), *range(k - 1, 0, -1)], np.uint64)
    has = int(state["has_uint32"])
    raw = bg.random_raw((len(bounds) * count - has + 1) // 2 + 1)
    words = np.stack([raw & np.uint64(0xFFFFFFFF), raw >> np.uint64(32)], 1).ravel()
    if has:
        words = np.concatenate([np.array([state["uinteger"]], np.uint64), words])
    u = words[: len(bounds) * count].reshape(count, len(bounds))
    m = u * (bounds + np.uint64(1))
    bg.state = state
    if np.any((m & np.uint64(0xFFFFFFFF)) < (np.uint64(0xFFFFFFFF) - bounds) % (bounds + 1)):
        return np.stack([rng.choice(n, k, replace=False) for _ in range(count)])
    v = (m >> np.uint64(32)).astype(np.int64)
    out = np.empty((count, k), np.int64)
    for t in range(k):  # Floyd: a value in [0, n - k + t], or n - k + t where taken already
        taken = (out[:, :t] == v[:, t : t + 1]).any(1)
        out[:, t] = np.where(taken, n - k + t, v[:, t])
    rows = np.arange(count)
    for t, i in enumerate(range(k - 1, 0, -1)):  # Fisher-Yates over the k taken
        j = v[:, k + t]
        out[rows, i], out[rows, j] = out[rows, j], out[rows, i].copy()
    # the generator as after the draws: the words used (the buffered half first, then
    # outputs), the unused half of the last output kept for the next 32-bit draw
    used = len(bounds) * count - has  # >= 4: k >= 3
    last = bg.random_raw((used + 1) // 2)[-1]
    after = bg.state
    after["has_uint32"], after["uinteger"] = (1, int(last >> np.uint64(32))) if used % 2 else (0, 0)
    bg.state = after
    return out


def _usable(s: np.ndarray, d: np.ndarray, tol: float, model: str, min_spread: float):
    """Samples worth a fit: not nearly collinear (nor coplanar, for the affine model),
    and, for a rigid model, with consistent pairwise distances."""
    area = np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1)
    ok = area > min_spread
    if model == "rigid":
        ds = np.linalg.norm(s[:, [0, 1, 2]] - s[:, [1, 2, 0]], axis=2)
        dd = np.linalg.norm(d[:, [0, 1, 2]] - d[:, [1, 2, 0]], axis=2)
        ok &= np.abs(ds - dd).max(1) < 2 * tol
    if model == "affine":
        A = np.concatenate([s, np.ones(s.shape[:2] + (1,))], 2)
        ok &= np.abs(np.linalg.det(A)) > min_spread**2
    return ok


def ransac(
    src: np.ndarray,
    dst: np.ndarray,
    tol: float,
    model: str = "rigid",
    iterations: int = 1000,
    seed: int = 0,
    min_spread: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC over minimal fits of `model` (rigid, similarity: 3 points; affine: 4),
    scored 256 hypotheses at a time, with an adaptive stop; then a least-squares refit on
    the inliers, grown once.

    src, dst : ndarray of shape (N, 3), matched points. tol : inlier distance.
    Returns (T of shape (4, 4) mapping src into dst, inlier mask of shape (N,)); the
    identity and no inliers when nothing fits. Raises NotEnoughCorrespondences with
    fewer matches than a sample.
    """
    k, fit = MODELS[model]
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if n < k:
        raise NotEnoughCorrespondences(f"RANSAC needs {k} correspondences, got {n}")
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    blocks = _usable_blocks(src, dst, k, iterations, rng, tol, model, min_spread)
    for block, trip in enumerate(blocks):
        lo = 256 * block  # 256 hypotheses at a time: memory bound to 256 x N points
        M, t = _minimal_fits(src[trip], dst[trip], model)
        inl = _within(M, t, src, dst, tol)
        j = inl.sum(1).argmax()
        if inl[j].sum() > best.sum():
            best = inl[j]
        # adaptive stop: enough samples for a 99.9% chance of one all-inlier sample
        w = best.sum() / n
        if w > 0 and lo + 256 >= np.log(1e-3) / np.log(max(1 - w**k, 1e-12)):
            break
    return _refit(src, dst, best, tol, fit, k)


def _within(M: np.ndarray, t: np.ndarray, src: np.ndarray, dst: np.ndarray, tol: float):
    """Which matches (src -> dst, (N, 3)) each of H models (M (H, 3, 3), t (H, 3)) puts
    within `tol`: bool (H, N). A batched matrix product and one squared norm in place: 3-4x
    the `einsum` and temporaries it replaces (256 models x 10,000 matches: 400 -> 110 ms),
    which were two thirds of RANSAC on a TUM pair (py-spy: 2.1 of 3.0 s)."""
    d = np.matmul(src, M.transpose(0, 2, 1))
    d += t[:, None]
    d -= dst
    return np.einsum("hni,hni->hn", d, d) < tol * tol


def _refit(src, dst, best: np.ndarray, tol: float, fit, k: int = 3):
    """A least-squares fit on the consensus `best`, grown once: (T, inlier mask)."""
    if best.sum() < k:
        return np.eye(4), np.zeros(len(src), bool)
    T = fit(src[best], dst[best])
    inl = residuals(T, src, dst) < tol
    if inl.sum() >= best.sum():
        best = inl
        T = fit(src[best], dst[best])
    return T, best


def ransac_rigid(
    src: np.ndarray,
    dst: np.ndarray,
    tol: float,
    iterations: int = 1000,
    seed: int = 0,
    min_spread: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """`ransac` with the rigid model (3-point Kabsch fits)."""
    return ransac(src, dst, tol, "rigid", iterations, seed, min_spread)


def ransac_guided(
    src: np.ndarray,
    dst: np.ndarray,
    tol: float,
    seed: int = 0,
    seeds: int = 300,
    per_seed: int = 32,
    keep: int = 256,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid RANSAC for matches of which a few percent are right. Each of up to `seeds`
    matches is sampled with `per_seed` pairs of the matches whose distance to it agrees in
    both point sets (within 2 tol, and farther than that from it): once its seed is right,
    a triplet is right with chance (right / agreeing)^2, where a uniform one is with
    (right / all)^3 (81 right among 3,700, SUN3D with ASIFT: about 700,000 uniform samples
    for a 99.9% chance). Each fit is counted among its seed's agreeing matches only (an
    inlier of a fit through a right seed agrees with it), the `keep` best then on all. The
    compatibility graph of SC^2-PCR (Chen et al., CVPR 2022), sampled rather than searched.
    SUN3D's kept second looks: 300 seeds of 32 found the right consensus as 1,000 of 16 did,
    in half the time (3 against 6.5 s for the six sets of 4,000-5,000 matches); a `keep` of
    32 lost it among variants of a larger one.
    Returns (T mapping src into dst, inlier mask), as `ransac_rigid`."""
    n, rng = len(src), np.random.default_rng(seed)
    order = rng.permutation(n)[:seeds]
    found: list[tuple[int, np.ndarray]] = []
    for lo in range(0, len(order), 256):
        s = order[lo : lo + 256]
        dx = np.linalg.norm(src[s, None] - src[None], axis=2)
        dy = np.linalg.norm(dst[s, None] - dst[None], axis=2)
        agree = (np.abs(dx - dy) < 2 * tol) & (dx > 2 * tol)
        for i, row in zip(s, agree, strict=True):
            local = np.flatnonzero(row)
            if len(local) >= 2:
                found += _seeded_fits(src, dst, i, local, tol, rng, per_seed)
    if not found:
        return np.eye(4), np.zeros(n, bool)
    found.sort(key=lambda f: -f[0])
    best = np.zeros(n, bool)
    for _, T in found[:keep]:
        inl = residuals(T, src, dst) < tol
        if inl.sum() > best.sum():
            best = inl
    return _refit(src, dst, best, tol, kabsch)


def _seeded_fits(src, dst, i: int, local: np.ndarray, tol: float, rng, per_seed: int):
    """The best of `per_seed` triplets (i, j, m), j and m among `local`, counted on
    `local`: [(count, T)] or []."""
    jm = local[rng.integers(0, len(local), (per_seed, 2))]
    trip = np.column_stack([np.full(len(jm), i), jm])[jm[:, 0] != jm[:, 1]]
    s, d = src[trip], dst[trip]
    ok = _usable(s, d, tol, "rigid", 1e-3)
    if not ok.any():
        return []
    M, t = _batch_kabsch(s[ok], d[ok])
    count = _within(M, t, src[local], dst[local], tol).sum(1)
    j = int(count.argmax())
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = M[j], t[j]
    return [(int(count[j]), T)]
