"""A second look at a pair the gate refused: raw matches of affine-simulated SIFT.

MSER+SIFT matches surfaces seen from directions up to about 40-50 degrees apart. Robots that
pass through the same room facing the other way, or circle a desk, see the same surfaces
from farther apart, and their views share almost no matches that agree (HoloLens walk, 51%
of the maps shared: 1 of 730 raw matches within 8 cm of the truth). ASIFT simulates the
tilts in between (`fleetmap.features.affine_features`): on those views 16-19 of 24-40
matches agree with the truth. It costs about ten times SIFT, so it runs only where the
first look was refused, on a few views of each robot, and its matches join the first
look's raw matches: the same hypotheses, free-space test and gate judge them all.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numpy as np

from fleetmap.align.types import SecondLook, unique_views
from fleetmap.correspondences import Correspondences, lift
from fleetmap.feature_cache import Recent, cached_local, digest
from fleetmap.features import SIFT_LAYERS, SIFT_SIGMA, LocalFeatures, affine_features
from fleetmap.matching import distinct_second, match_descriptors, single_threaded_products


def spread_views(views: list, n: int) -> list:
    """At most n of the views, evenly over the list (the first look's views are in time
    order, so over the robot's path near the overlap)."""
    if len(views) <= n:
        return views
    return [views[int(k)] for k in np.linspace(0, len(views) - 1, n).round()]


_FEATURES = Recent(48)  # about 6,000 features (0.8 MB) a view
_MATCHES = Recent(1024)


def _affine(image: np.ndarray, max_tilt: int, per_view: int) -> LocalFeatures:
    """`affine_features`, kept by `fleetmap.feature_cache` where one is on."""
    detect = partial(affine_features, image, max_tilt, per_view)
    return cached_local(image, detect, "asift", max_tilt, per_view, SIFT_LAYERS, SIFT_SIGMA)


def affine_matches(pairs, first_index: int, s: SecondLook) -> Correspondences:
    """Raw (mutual, ratio-test) ASIFT matches of every pair of `s.views` views of each
    robot, lifted to 3D in each robot's map frame; pair indices from `first_index` on.
    Features and matches of views seen in recent requests are reused (`feature_cache.Recent`)."""
    va = spread_views(unique_views(pairs, 0), s.views)
    vb = spread_views(unique_views(pairs, 1), s.views)
    views = va + vb
    keys = [(digest(v.rgb), s.max_tilt, s.per_view) for v in views]

    def features(k: int):
        return _FEATURES.get(keys[k], lambda: _affine(views[k].rgb, *keys[k][1:]))

    with ThreadPoolExecutor(2) as ex:  # OpenCV releases the GIL
        feats = list(ex.map(features, range(len(views))))
    fa, fb = feats[: len(va)], feats[len(va) :]
    # each B view's keypoints near one another: once a view, not once a view pair
    near = [distinct_second(f.keypoints, s.distinct_px) if s.distinct_px > 0 else None for f in fb]
    grid = [(a, b) for a in range(len(va)) for b in range(len(vb))]

    def match(ab: tuple[int, int]):
        a, b = fa[ab[0]].descriptors, fb[ab[1]].descriptors
        key = (keys[ab[0]], keys[len(va) + ab[1]], s.ratio, s.distinct_px)
        return _MATCHES.get(key, lambda: match_descriptors(a, b, s.ratio, near[ab[1]]))

    # the products, maxima and sorts release the GIL; each thread's products on one core
    with ThreadPoolExecutor(2, initializer=single_threaded_products) as ex:
        found = list(ex.map(match, grid))
    out = [
        lift(va[a], vb[b], fa[a], fb[b], ia, ib, first_index + k)
        for k, ((a, b), (ia, ib)) in enumerate(zip(grid, found, strict=True))
    ]
    return Correspondences.concat(out)
