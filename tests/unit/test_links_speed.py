"""Issue 23: link overlaps with each keyframe's side of the co-visibility test computed once
(`covisibility_many`, `link_rows`) give exactly what the per-pair test gave: the same scores
for every keyframe pair and the same link rows, on real keyframes (SUN3D, HoloLens) under
their true transforms. The per-pair reference is the code as it was before (fcd21bd)."""

from __future__ import annotations

import numpy as np
import pytest

from fleetmap.dataset import read_recording
from fleetmap.extract import keyframe_indices
from fleetmap.extract_pool import extract_keyframes
from fleetmap.frame import Frame
from fleetmap.place.cascade import (
    covis_source,
    covis_target,
    covisibility_many,
    sparse_covisibility,
)
from fleetmap.place.links import (
    LINK_MIN_POINTS,
    LINK_MIN_SHARE,
    LINK_NEAR_M,
    CovisCache,
    centre,
    link_rows,
)


def old_sparse_covisibility(target, source, T_target_source, radius_px=24.0):
    """`fleetmap.place.cascade.sparse_covisibility` at fcd21bd, verbatim."""
    if (
        target.points is None
        or source.points is None
        or target.T_map_cam is None
        or target.intrinsics is None
    ):
        return 0, 0.0
    from scipy.spatial import cKDTree

    K = target.intrinsics
    cam = np.linalg.inv(target.T_map_cam)
    pa = target.points[target.point_valid].astype(np.float64) @ cam[:3, :3].T + cam[:3, 3]
    M = cam @ T_target_source
    pb = source.points[source.point_valid].astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    pa = pa[pa[:, 2] > 0.1]
    if not len(pa) or not len(pb):
        return 0, 0.0
    z = pb[:, 2]
    front = z > 0.1
    zf = z[front]
    ub = K.project(pb[front])
    inside = (ub[:, 0] >= 0) & (ub[:, 0] < K.width) & (ub[:, 1] >= 0) & (ub[:, 1] < K.height)
    if not inside.any():
        return 0, 0.0
    ua = K.project(pa)
    d, k = cKDTree(ua).query(ub[inside], distance_upper_bound=radius_px)
    near = np.isfinite(d)
    za, zb = pa[k[near], 2], zf[inside][near]
    n = int(np.count_nonzero(np.abs(zb - za) < 0.1 + 0.05 * za))
    return n, n / len(pb)


def old_link_rows(xs, rx, ys, ry, T_y_x):
    """`fleetmap.place.links.link_rows` at fcd21bd, verbatim."""
    out = []
    cy = np.array([centre(fy) for _, fy in ys]).reshape(-1, 3)
    for kx, fx in xs:
        best = None
        c = T_y_x[:3, :3] @ centre(fx) + T_y_x[:3, 3]
        for k in np.flatnonzero(np.linalg.norm(cy - c, axis=1) < LINK_NEAR_M):
            ky, fy = ys[k]
            seen, share = old_sparse_covisibility(fy, fx, T_y_x)
            ok = seen >= LINK_MIN_POINTS and share >= LINK_MIN_SHARE
            if ok and (best is None or seen > best[4]):
                n_pts = int(fx.point_valid.sum()) if fx.point_valid is not None else 0
                best = (kx, rx, ky, ry, seen, n_pts)
        if best is not None:
            out.append(best)
    return out


def assert_same(fa: list[Frame], fb: list[Frame], T_a_b: np.ndarray) -> int:
    """Every pair's score both ways and the link rows both ways equal the old code's;
    returns the number of link rows."""
    xs_a = [(i, f) for i, f in enumerate(fa)]
    xs_b = [(1000 + i, f) for i, f in enumerate(fb)]
    for targets, sources, T in ((fa, fb, T_a_b), (fb, fa, np.linalg.inv(T_a_b))):
        src = [covis_source(s) for s in sources]
        for t in targets:
            old = [old_sparse_covisibility(t, s, T) for s in sources]
            assert covisibility_many(covis_target(t), src, T) == old
            assert [sparse_covisibility(t, s, T) for s in sources[:3]] == old[:3]
    cache = CovisCache()  # shared by both directions, as pair_link_rows does
    new = link_rows(xs_b, 2, xs_a, 1, T_a_b, cache)
    new += link_rows(xs_a, 1, xs_b, 2, np.linalg.inv(T_a_b), cache)
    old = old_link_rows(xs_b, 2, xs_a, 1, T_a_b)
    old += old_link_rows(xs_a, 1, xs_b, 2, np.linalg.inv(T_a_b))
    assert new == old
    return len(new)


def test_sun3d_link_overlaps_are_unchanged(sun3d, sun3d_keyframes):
    T = np.loadtxt(sun3d / "T_a_b.txt")
    n = assert_same(sun3d_keyframes["robot_a"], sun3d_keyframes["robot_b"], T)
    assert n > 0  # the pair shares a room: some keyframes are linked


@pytest.fixture(scope="module")
def hololens_frames(hololens) -> dict[str, list[Frame]]:
    """Every third keyframe of the HoloLens robots, as the merge extracts them (in this
    process: a unit test starts no process)."""
    recs = [read_recording(hololens / r, robot_id=r) for r in ("hl_a", "hl_b")]
    index = {r.robot_id: keyframe_indices(r)[::3] for r in recs}
    out: dict[str, list[Frame]] = {}
    for kf in extract_keyframes(recs, index, workers=1):
        out.setdefault(kf.robot_id, []).append(kf.frame)
    return out


def test_hololens_link_overlaps_are_unchanged(hololens, hololens_frames):
    T = np.loadtxt(hololens / "T_a_b.txt")
    n = assert_same(hololens_frames["hl_a"], hololens_frames["hl_b"], T)
    assert n >= 20  # hl_b revisits hl_a's kitchen and lounge


def test_a_keyframe_without_depth_or_pose_sees_nothing(sun3d, sun3d_keyframes):
    a, b = sun3d_keyframes["robot_a"][0], sun3d_keyframes["robot_b"][0]
    T = np.loadtxt(sun3d / "T_a_b.txt")
    blind = Frame(**{**vars(a), "T_map_cam": None})
    flat = Frame(**{**vars(b), "points": None, "point_valid": None})
    assert covis_target(blind) is None and len(covis_source(flat)) == 0
    assert sparse_covisibility(blind, b, T) == old_sparse_covisibility(blind, b, T) == (0, 0.0)
    assert sparse_covisibility(a, flat, T) == old_sparse_covisibility(a, flat, T) == (0, 0.0)
    assert covisibility_many(covis_target(a), [covis_source(flat)], T) == [(0, 0.0)]


class _Store:
    """The two calls LinkOverlaps makes of a store: robot 2 linked into robot 1."""

    def __init__(self, ids: dict[int, list[int]], T_1_2: np.ndarray):
        self.ids, self.T = ids, T_1_2

    def links(self, code):
        return [(1, 2, self.T, 0.0)]

    def robot_keyframe_ids(self, code):
        return self.ids[code]


@pytest.mark.parametrize("size", [512, 3])  # 3: most targets evicted and loaded again
def test_live_link_overlaps_are_unchanged(hololens, hololens_frames, size, monkeypatch):
    """Each new keyframe's link overlaps (`LinkOverlaps`, prepared targets kept between
    keyframes) equal the old per-pair code's on fresh frames, both robots streaming."""
    import fleetmap.place.links as links

    monkeypatch.setattr(links, "LINK_CACHE", size)
    T = np.loadtxt(hololens / "T_a_b.txt")
    frames = {i: f for i, f in enumerate(hololens_frames["hl_a"])}
    frames |= {1000 + i: f for i, f in enumerate(hololens_frames["hl_b"])}
    ids = {1: sorted(i for i in frames if i < 1000), 2: sorted(i for i in frames if i >= 1000)}
    loads = []
    live = links.LinkOverlaps(_Store(ids, T), lambda i: loads.append(i) or frames[i])
    xs = {c: [(i, frames[i]) for i in ids[c]] for c in ids}
    for passes in range(2):
        loads.clear()
        n = 0
        for code, other, T_o in ((2, 1, T), (1, 2, np.linalg.inv(T))):
            for kx, fx in xs[code]:
                old = old_link_rows([(kx, fx)], code, xs[other], other, T_o)
                assert live.for_keyframe(kx, fx, code) == old
                n += len(old)
        assert n >= 20
        if size == 512 and passes == 1:
            assert loads == []  # every centre and target was kept: nothing read again
