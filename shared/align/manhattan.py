"""Starts for the third look from the maps' dominant planes (a Manhattan frame), where FPFH
matches fail.

Rooms, corridors, kitchens and desks are built of a few plane orientations: floor, walls,
table tops. Each map's two strongest surface-normal directions (and their cross product)
give it a frame; the rotation between two maps is then one of the 24 that carry one frame's
axes onto the other's (a cube's rotations: which axis is which, and their signs), whatever
each robot saw of the room. For each rotation, the translations where the two maps'
occupancy grids correlate most (one FFT) are the starts, refined by ICP and judged like the
FPFH basins (`fleetmap.align.geometric_look`).

Why: where two robots saw the same room from directions far apart, FPFH's histograms of
the two partial views differ (HoloLens walk, 20% of B's map shared: 3-13 of 4,000-13,000
FPFH correspondences agree with the truth at three voxels, and no RANSAC seed lands near
it), while the dominant planes are the same planes: the rotation among the 24 was 1.6 deg
from the truth, and a translation peak 0.14 m from it (docs/ALIGNER.md).
"""

from __future__ import annotations

import itertools

import numpy as np

#: a normal within this of a direction counts for it (degrees)
NORMAL_TOL_DEG = 8.0
#: the second direction's normals lie within this of perpendicular to the first's
PERPENDICULAR_TOL_DEG = 10.0
#: each of the two directions needs this share of the normals: fewer for the second, and
#: the map has one plane orientation only (a floor, a table top) and no frame
MIN_SHARE = 0.03
#: translations tried per rotation (local maxima of the occupancy correlation); on the
#: HoloLens pairs the right one was the best or second best of all 144 at two voxels
PEAKS = 6


def dominant_frame(normals: np.ndarray) -> np.ndarray | None:
    """3x3 rotation whose columns are the normals' strongest direction, the strongest one
    perpendicular to it, and their cross product; None where the second is too weak."""
    n = np.asarray(normals, np.float64)
    if len(n) < 50:
        return None
    dirs = np.random.default_rng(0).normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    d1, count = _peak(n, dirs)
    if count < MIN_SHARE * len(n) or not np.isfinite(d1).all():
        return None  # no direction holds even a few normals (zero or scattered normals)
    perp = n[np.abs(n @ d1) < np.sin(np.radians(PERPENDICULAR_TOL_DEG))]
    if len(perp) < MIN_SHARE * len(n):
        return None
    flat = dirs - (dirs @ d1)[:, None] * d1
    flat /= np.maximum(np.linalg.norm(flat, axis=1), 1e-9)[:, None]
    d2, count = _peak(perp, flat)
    if count < MIN_SHARE * len(n):
        return None
    d2 = d2 - (d2 @ d1) * d1
    d2 /= np.linalg.norm(d2)
    return np.stack([d1, d2, np.cross(d1, d2)], axis=1)


def _peak(n: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, int]:
    """The direction (sign-free) with the most normals within NORMAL_TOL_DEG, refined to
    their mean, and how many those are."""
    cos = np.cos(np.radians(NORMAL_TOL_DEG))
    counts = (np.abs(n @ dirs.T) > cos).sum(0)
    d = dirs[int(np.argmax(counts))]
    near = n[np.abs(n @ d) > cos]
    if len(near) == 0:
        return d, 0
    near = near * np.sign(near @ d)[:, None]
    mean = near.mean(0)
    return mean / np.linalg.norm(mean), int(counts.max())


def cube_rotations() -> list[np.ndarray]:
    """The 24 rotations that carry the coordinate axes onto themselves."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            P = np.zeros((3, 3))
            P[range(3), perm] = signs
            if np.linalg.det(P) > 0:
                out.append(P)
    return out


def translation_peaks(
    A: np.ndarray, B: np.ndarray, cell: float, k: int
) -> list[tuple[np.ndarray, float]]:
    """The `k` translations t (local maxima, strongest first) where the occupancy grids of
    points A and of B + t overlap most, at `cell` metres, with how many cells overlap
    there: one FFT cross-correlation."""
    from scipy import fft, ndimage

    lo_a, lo_b = A.min(0), B.min(0)
    ia = np.floor((A - lo_a) / cell).astype(int)
    ib = np.floor((B - lo_b) / cell).astype(int)
    shape = tuple(int(s) for s in ia.max(0) + ib.max(0) + 2)
    ga, gb = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    ga[tuple(ia.T)] = 1.0
    gb[tuple(ib.T)] = 1.0
    corr = fft.irfftn(fft.rfftn(ga) * np.conj(fft.rfftn(gb)), s=shape, workers=2)
    peaks = np.flatnonzero((corr == ndimage.maximum_filter(corr, 3, mode="wrap")) & (corr > 0))
    best = peaks[np.argsort(corr.ravel()[peaks])[::-1][:k]]
    out = []
    for f in best:
        idx = np.array(np.unravel_index(f, shape))
        shift = np.where(idx > np.array(shape) / 2, idx - np.array(shape), idx)
        out.append((shift * cell + lo_a - lo_b, float(corr.ravel()[f])))
    return out


def manhattan_starts(cloud_a, cloud_b, voxel: float, n: int) -> list[np.ndarray]:
    """The `n` starting T_a_b (4x4) for ICP where the most occupied cells meet: the 24
    rotations between the two clouds' dominant frames (Open3D clouds with normals, at
    `voxel`), each with its PEAKS best translations at two voxels, ranked together by the
    cells they overlap. Empty where either map has no second plane orientation."""
    fa = dominant_frame(np.asarray(cloud_a.normals))
    fb = dominant_frame(np.asarray(cloud_b.normals))
    if fa is None or fb is None or n < 1:
        return []
    A, B = np.asarray(cloud_a.points), np.asarray(cloud_b.points)
    ranked = []
    for P in cube_rotations():
        R = fa @ P @ fb.T
        for t, cells in translation_peaks(A, B @ R.T, 2 * voxel, PEAKS):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            ranked.append((cells, len(ranked), T))
    ranked.sort(key=lambda r: (-r[0], r[1]))
    return [T for _, _, T in ranked[:n]]
