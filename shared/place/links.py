"""Links: map alignments registered by the aligner, and the keyframe pairs they make
co-visible. Wide baselines defeat keyframe-level visual verification (SUN3D: even under the
true transform, 2 of 13 keyframes share 4 matching features) where the whole-map alignment
succeeds; with a link, the overlap graph covers what the robots really share."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from fleetmap.frame import Frame
from fleetmap.geometry import invert
from fleetmap.place.cascade import CovisTarget, covis_source, covis_target, covisibility_many
from fleetmap.place.store import LinkRow, Store

LINK_NEAR_M = 4.0  # keyframes whose seen points' centres are farther apart share nothing
LINK_MIN_POINTS = 15  # points of x seen by y, at least
LINK_MIN_SHARE = 0.15  # and this share of x's points
LINK_CACHE = 512  # keyframes whose co-visibility side a place database keeps prepared


def centre(f: Frame) -> np.ndarray:
    """Mean of a frame's valid map points, shape (3,); inf without any."""
    if f.points is None or f.point_valid is None or not f.point_valid.any():
        return np.full(3, np.inf)
    return f.points[f.point_valid].astype(np.float64).mean(0)


class CovisCache:
    """Each keyframe's side of the co-visibility test (`covis_target`, `covis_source`),
    computed once per keyframe id however many pairs it is in. With `load` (id -> frame) a
    target missing from the cache is loaded from storage; with `size`, only the most
    recently used `size` keyframes of each side are kept."""

    def __init__(self, load: Callable[[int], Frame] | None = None, size: int | None = None):
        self.load, self.size = load, size
        self._targets: OrderedDict[int, CovisTarget | None] = OrderedDict()
        self._sources: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def target(self, kf_id: int, f: Frame | None) -> CovisTarget | None:
        return self._get(
            self._targets, kf_id, lambda: covis_target(self.load(kf_id) if f is None else f)
        )

    def source(self, kf_id: int, f: Frame) -> np.ndarray:
        return self._get(self._sources, kf_id, lambda: covis_source(f))

    def _get(self, d: OrderedDict, kf_id: int, make: Callable):
        with self._lock:  # overlap workers share a place database's cache
            if kf_id in d:
                d.move_to_end(kf_id)
                return d[kf_id]
        value = make()
        with self._lock:
            d[kf_id] = value
            while self.size is not None and len(d) > self.size:
                d.popitem(last=False)
        return value


def link_rows(xs, rx: int, ys, ry: int, T_y_x: np.ndarray, cache=None, cy=None) -> list[LinkRow]:
    """For each keyframe x (id, frame) of robot rx, its most co-visible keyframe of robot ry
    under T_y_x (rx's map into ry's): rows (kf_x, rx, kf_y, ry, points seen, points).
    Each y is tested against all the xs near it at once (`covisibility_many`). Given the
    ys' centres `cy` and a `cache` that loads, a y's frame may be None (not read)."""
    cache = CovisCache() if cache is None else cache
    if cy is None:
        cy = np.array([centre(fy) for _, fy in ys]).reshape(-1, 3)
    near = []
    for _, fx in xs:
        c = centre(fx)
        if not np.isfinite(c).all():  # no map point (no depth reading): near nothing
            near.append(np.zeros(0, np.intp))
            continue
        c = T_y_x[:3, :3] @ c + T_y_x[:3, 3]
        near.append(np.flatnonzero(np.linalg.norm(cy - c, axis=1) < LINK_NEAR_M))
    by_y: dict[int, list[int]] = {}
    for i, ks in enumerate(near):
        for k in ks:
            by_y.setdefault(int(k), []).append(i)
    scores: dict[tuple[int, int], tuple[int, float]] = {}
    for k, idx in by_y.items():
        target = cache.target(*ys[k])
        sources = [cache.source(*xs[i]) for i in idx]
        for i, score in zip(idx, covisibility_many(target, sources, T_y_x), strict=True):
            scores[i, k] = score
    out = []
    for i, (kx, fx) in enumerate(xs):
        best = None
        for k in near[i]:
            seen, share = scores[i, int(k)]
            if seen >= LINK_MIN_POINTS and share >= LINK_MIN_SHARE:
                if best is None or seen > best[4]:
                    n_pts = int(fx.point_valid.sum()) if fx.point_valid is not None else 0
                    best = (kx, rx, ys[k][0], ry, seen, n_pts)
        if best is not None:
            out.append(best)
    return out


def pair_link_rows(store: Store, load, ra: int, rb: int, T_a_b: np.ndarray) -> list[LinkRow]:
    """Link rows both ways between two robots' whole keyframe sets; each keyframe's side of
    the co-visibility test is computed once for both."""
    fa = [(i, load(i)) for i in store.robot_keyframe_ids(ra)]
    fb = [(i, load(i)) for i in store.robot_keyframe_ids(rb)]
    cache = CovisCache()
    return link_rows(fb, rb, fa, ra, T_a_b, cache) + link_rows(fa, ra, fb, rb, invert(T_a_b), cache)


class LinkOverlaps:
    """Link overlaps of each new keyframe with the robots its robot is linked to. Only the
    other robot's keyframes near the new one are read from storage: their point centres
    are cached (24 bytes each) after the first look, and the co-visibility side of the
    `LINK_CACHE` most recently near ones (a KD-tree of pixels and depths, some 40 KB)."""

    def __init__(self, store: Store, load: Callable[[int], Frame]):
        self.store, self.load = store, load
        self._centres: dict[int, np.ndarray] = {}
        self._covis = CovisCache(load, LINK_CACHE)

    def for_keyframe(self, kf_id: int, frame: Frame, code: int) -> list[LinkRow]:
        rows: list[LinkRow] = []
        for a, b, T_a_b, _ in self.store.links(code):
            other, T_other_this = (a, T_a_b) if b == code else (b, invert(T_a_b))
            ids = self.store.robot_keyframe_ids(other)
            for i in ids:
                if i not in self._centres:
                    self._centres[i] = centre(self.load(i))
            c = T_other_this[:3, :3] @ centre(frame) + T_other_this[:3, 3]
            near = [i for i in ids if np.linalg.norm(self._centres[i] - c) < LINK_NEAR_M]
            cy = np.array([self._centres[i] for i in near]).reshape(-1, 3)
            ys = [(i, None) for i in near]  # loaded by the cache where not prepared yet
            xs = [(kf_id, frame)]
            rows += link_rows(xs, code, ys, other, T_other_this, self._covis, cy)
        return rows
