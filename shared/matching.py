"""SIFT matching and epipolar verification (thesis eq. 2.10, Algorithm 3 step 2).

Matches pass Lowe's ratio test and a mutual-nearest check; with N > 8 matches a
fundamental matrix is fitted by OpenCV's USAC (MAGSAC++) and its inliers counted. Eight
points always fit some F, so a verified pair also needs `min_epipolar_inliers` inliers and an inlier
ratio: that is what keeps look-alike corridors from producing false winners.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MatchParams:
    """Ratio test, the thesis's N > 8, and what a verified pair needs."""

    ratio: float = 0.9
    min_matches: int = 9
    ransac_px: float = 2.0
    confidence: float = 0.999
    min_epipolar_inliers: int = 20
    min_inlier_ratio: float = 0.3
    # With depth on both sides: fewer epipolar inliers suffice when enough of them also
    # agree with one rigid motion of their 3D points (a test random matches fail).
    min_inliers_3d_check: int = 10
    min_rigid_inliers: int = 6
    rigid_tol_m: float = 0.1


DEFAULT_MATCH_PARAMS = MatchParams()


@dataclass(frozen=True)
class Verification:
    """Outcome of matching two frames: indices into each side's features."""

    matches: int
    inliers: int
    idx_a: np.ndarray  # (M,) feature indices of frame a (inliers only when verified)
    idx_b: np.ndarray
    verified: bool
    match_ms: float = 0.0
    ransac_ms: float = 0.0
    rigid_inliers: int = -1  # -1: no 3D check made


def match_descriptors(
    da: np.ndarray, db: np.ndarray, ratio: float, near: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test, mutually nearest matches between descriptor sets (Na, 128) and (Nb, 128).

    `near`: `distinct_second` of b's keypoints: the ratio test's second nearest is the
    nearest b not near the nearest's keypoint.
    Returns index arrays (M,) into a and into b.
    """
    return match_descriptors_at(da, db, (ratio,), near)[0]


def distinct_second(keypoints: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """For each keypoint, the keypoints within `radius_px` of it (itself included), as CSR
    (indptr (N + 1,), indices): the ones a ratio test must not take for its second nearest.

    Lowe's ratio test presumes that a point of the scene is described once, so that the
    second nearest descriptor is another point. Affine-simulated SIFT describes one point
    under several simulated tilts: on HoloLens views 71% of the features have their nearest
    other descriptor at a keypoint within 3 px, and the ratio test then refuses the match
    for being ambiguous with the same point (docs/ALIGNER.md, session 22)."""
    from scipy.spatial import cKDTree

    xy = np.asarray(keypoints, np.float64)
    near = cKDTree(xy).query_ball_point(xy, radius_px, return_sorted=False)
    counts = np.fromiter(map(len, near), np.intp, len(near))
    indptr = np.concatenate([[0], np.cumsum(counts)])
    indices = np.concatenate([np.asarray(x, np.intp) for x in near]) if len(near) else counts
    return indptr, indices


def match_descriptors_at(
    da: np.ndarray,
    db: np.ndarray,
    ratios: tuple[float, ...],
    near: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """`match_descriptors` at several ratio thresholds from one distance computation."""
    if len(da) < 2 or len(db) < 2:
        return [(np.zeros(0, int), np.zeros(0, int)) for _ in ratios]
    fa, fb = da.astype(np.float32), db.astype(np.float32)
    na, nb = (fa * fa).sum(1), (fb * fb).sum(1)
    product = _products(da, db)
    best = np.empty(len(fa), np.intp)
    s1, s2 = np.empty(len(fa), np.float32), np.empty(len(fa), np.float32)
    mutual = np.zeros(len(fa), bool)
    top = np.full(len(fb), -np.inf, np.float32)  # each column's best so far
    first = np.zeros(len(fb), np.intp)  # the block where it was first reached
    for k, lo in enumerate(range(0, len(fa), _BLOCK)):
        rows = slice(lo, lo + _BLOCK)
        S = product(rows) if product else fa[rows] @ fb.T
        best[rows], s1[rows], s2[rows], mutual[rows], m = _block(S, na[rows], nb, near)
        up = m > top
        top[up], first[up] = m[up], k
    # a row is its best column's best row where that column's maximum is its value and was
    # first reached in the row's block (ties: the first row stands, as argmax's)
    blocks = np.arange(len(fa)) // _BLOCK
    mutual &= (((s1 + nb[best]) - na) >= top[best]) & (first[best] == blocks)
    d_best, d_second = np.maximum(na - s1, 0), np.maximum(na - s2, 0)
    out = []
    for ratio in ratios:
        ia = np.flatnonzero((d_best < (ratio**2) * d_second) & mutual)
        out.append((ia, best[ia]))
    return out


#: Rows of the similarity matrix computed at a time: 256 x 7,000 floats (7 MB) stay in the
#: cache for the passes over them, where the whole matrix (7,000 x 8,000, 224 MB) went to
#: memory for each. HoloLens ASIFT views, the second look's two threads: 0.40 -> 0.22 s a
#: view pair (64-512 rows: 0.22-0.25 s), the same matches (session 13).
_BLOCK = 256


#: Products of at least this many entries are made by torch where it is installed (the
#: aligner's `server` extra): the second look's 6,000 x 7,000 ASIFT matchings; the place
#: database's few hundred features a keyframe stay in numpy.
TORCH_MIN_ENTRIES = 4_000_000


def _products(da: np.ndarray, db: np.ndarray):
    """rows -> the block da[rows] . db^T of uint8 descriptors, as float32, from
    torch's 8-bit integer product (`torch._int_mm`, VNNI where the CPU has it), or None
    where numpy's is used. Exact: the descriptors shifted to int8, a' = a - 128, give
    a.b = a'.b' + 128 (sum a + sum b) - 128^2 d for length d; every term and sum is an
    integer under 2^24 for d up to 258, which float32 holds, so the matches are the same to
    the bit as numpy's product. torch's, not numpy's, because the second look runs two
    matchings at once: OpenBLAS's thread count is the process's, and two calls that each
    want its two threads wait on each other, where torch's is each thread's own
    (`single_threaded_products`). A HoloLens pair's 36 matchings (6 x 6 ASIFT views, two
    threads, each on one core, quiet): float32 2.46 s wall / 4.85 s CPU, 8-bit 1.06 s / 2.05
    s, the same 13,688 matches; one matching's products 0.155 -> 0.053 s (session 55).
    Session 43 had measured the 8-bit product slower (4.0 s) while each matching's product
    still ran on two threads, four on two cores.
    Importing torch takes 0.75-1 s the first time: the aligner service imports it then."""
    exact = da.dtype == np.uint8 and db.dtype == np.uint8 and da.shape[1] <= 258
    if not exact or len(da) * len(db) < TORCH_MIN_ENTRIES:
        return None
    torch = _torch()
    if torch is None:
        return None
    a8 = torch.from_numpy((da.astype(np.int16) - 128).astype(np.int8))
    b8 = torch.from_numpy((db.astype(np.int16) - 128).astype(np.int8)).T
    col = 128.0 * db.sum(1, dtype=np.float32) - 128.0**2 * db.shape[1]
    row = 128.0 * da.sum(1, dtype=np.float32)

    def block(rows: slice) -> np.ndarray:
        # the corrections in numpy: torch's broadcast add of int32 on one core took 5 ms
        # a block, numpy's 1 ms
        S = torch._int_mm(a8[rows], b8).numpy().astype(np.float32)
        S += col[None, :]
        S += row[rows, None]
        return S

    return block


def _torch():
    """The torch module, or None where it is not installed (a robot's install)."""
    try:
        import torch
    except ImportError:
        return None
    return torch


def single_threaded_products() -> None:
    """This thread's torch products on one core (a pool's initializer, where each worker
    runs whole matchings): two at once then keep two cores busy instead of four threads
    spinning on them. OpenMP's thread count is per thread (`omp_set_num_threads` of the
    OpenMP torch loaded); `torch.set_num_threads` is not: it also sets what every thread
    that first uses torch after it starts with. Nothing where torch is absent or runs
    another OpenMP."""
    torch = _torch()
    if torch is None:
        return
    import ctypes
    import os

    try:  # the copy torch loaded, never another one
        gomp = ctypes.CDLL(
            os.path.join(os.path.dirname(torch.__file__), "lib", "libgomp.so.1"),
            mode=os.RTLD_NOLOAD | os.RTLD_LAZY,
        )
    except OSError:
        return
    torch.get_num_threads()  # torch's own first-use set-up of this thread, before ours
    gomp.omp_set_num_threads(1)


def _block(S: np.ndarray, na: np.ndarray, nb: np.ndarray, near=None):
    """For a block of rows of a, given S = a.b^T: each row's nearest b (best), the two
    smallest |b|^2 - 2 a.b (the second among the columns not `near` the best's, where
    given: `distinct_second`'s CSR), whether the row is the first in the block to reach its
    best column's maximum (in the block), and each column's maximum of 2 a.b - |a|^2 in
    the block."""
    # |a - b|^2 = na + nb - 2 a.b: a row's nearest b maximises 2 a.b - nb, a column's
    # nearest a maximises 2 a.b - na. One matrix product, then passes over it in place.
    S *= 2.0
    S -= nb[None, :]
    rows = np.arange(len(S))
    best = S.argmax(1)
    s1 = S[rows, best].copy()
    r, c = (rows, best) if near is None else _near_cells(rows, best, *near)
    kept = S[r, c]
    S[r, c] = -np.inf
    s2 = S.max(1)
    S[r, c] = kept
    S += nb[None, :]
    S -= na[:, None]
    top = S.max(0)
    return best, s1, s2, mutual_best(S, rows, best, top), top


def _near_cells(rows, best, indptr, indices):
    """(row, column) of every column near each row's best column (CSR `indptr`, `indices`)."""
    start, count = indptr[best], indptr[best + 1] - indptr[best]
    first = np.cumsum(count) - count  # where each row's run starts in the output
    pos = np.arange(int(count.sum())) - np.repeat(first - start, count)
    return np.repeat(rows, count), indices[pos]


def mutual_best(
    S: np.ndarray, rows: np.ndarray, best: np.ndarray, top: np.ndarray | None = None
) -> np.ndarray:
    """Whether row i is also column best[i]'s best row (`S.argmax(0)[best] == rows`)
    from the columns' maxima: numpy's argmax down the columns of a row-major matrix took
    66 of a 3,600 x 3,600 matching's 160 ms (17-18 % of the second look's samples), the
    maxima 3 ms. Where rows tie on a column's maximum (integer descriptors give integer
    distances), the first row stands, as argmax's: looked up in those columns only.
    `top`: the columns' maxima, when already computed."""
    top = S.max(0) if top is None else top
    mutual = S[rows, best] >= top[best]
    cand = np.flatnonzero(mutual)
    cols = best[cand]
    first = (np.take(S, cols, axis=1) == top[cols]).argmax(0)
    mutual[cand] = first == cand
    return mutual


def verify_pair(
    kp_a: np.ndarray,
    desc_a: np.ndarray,
    kp_b: np.ndarray,
    desc_b: np.ndarray,
    params: MatchParams = DEFAULT_MATCH_PARAMS,
    points_a: tuple[np.ndarray, np.ndarray] | None = None,
    points_b: tuple[np.ndarray, np.ndarray] | None = None,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> Verification:
    """Match two frames' features and verify them with a fundamental-matrix RANSAC.

    kp_*: ndarray of shape (N, 2) pixel positions; desc_*: ndarray of shape (N, 128).
    points_*: optional (points (N, 3), valid (N,)) of each feature in its robot's map;
    with both, a pair the epipolar test did not verify but with `min_inliers_3d_check`
    epipolar inliers is verified when `min_rigid_inliers` of them agree with one rigid
    motion. `matches`: the descriptor
    matches at `params.ratio`, when already computed.
    """
    t0 = time.perf_counter()
    ia, ib = matches if matches is not None else match_descriptors(desc_a, desc_b, params.ratio)
    t1 = time.perf_counter()
    n = len(ia)
    if n < params.min_matches:
        return Verification(n, 0, ia, ib, False, 1000 * (t1 - t0))
    try:
        _, mask = cv2.findFundamentalMat(
            kp_a[ia].astype(np.float64),
            kp_b[ib].astype(np.float64),
            cv2.USAC_MAGSAC,
            params.ransac_px,
            params.confidence,
        )
    except cv2.error:  # USAC asserts on some degenerate samples: that is "not verified"
        mask = None
    ms = 1000 * (t1 - t0), 1000 * (time.perf_counter() - t1)
    if mask is None:
        return Verification(n, 0, ia, ib, False, *ms)
    inl = mask.ravel().astype(bool)
    k = int(inl.sum())
    ok = k >= params.min_epipolar_inliers and k >= params.min_inlier_ratio * n
    rigid = -1
    if (
        not ok
        and points_a is not None
        and points_b is not None
        and k >= params.min_inliers_3d_check
    ):
        rigid = _rigid_support(ia[inl], ib[inl], points_a, points_b, params.rigid_tol_m)
        ok = (ok or rigid >= params.min_rigid_inliers) and k >= params.min_inlier_ratio * n
    return Verification(n, k, ia[inl], ib[inl], ok, *ms, rigid_inliers=rigid)


def _rigid_support(ia, ib, points_a, points_b, tol: float) -> int:
    """How many matched features with depth on both sides fit one rigid motion."""
    from fleetmap.registration import ransac_rigid

    (pa, va), (pb, vb) = points_a, points_b
    both = va[ia] & vb[ib]
    if both.sum() < 3:
        return 0
    _, inl = ransac_rigid(pb[ib[both]], pa[ia[both]], tol)
    return int(inl.sum())
