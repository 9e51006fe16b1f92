"""From matched RGB-D pairs to 3D-3D correspondences between two robots' map frames.

SIFT matches between the two colour images, a fundamental-matrix RANSAC on them, depth
looked up at each inlier (missing depth and depth edges rejected), back-projection with
the intrinsics, and each point into its robot's map frame with the frame's camera-to-map
pose. Several pairs spread over the overlap are pooled (thesis Table 3.5: spread matters
more than count).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from fleetmap.camera import Intrinsics, backproject_pixels
from fleetmap.errors import BadInput, NoDepthReading
from fleetmap.feature_cache import Recent, cached_local, digest
from fleetmap.features import FeatureParams, LocalFeatures, detect_and_describe
from fleetmap.geometry import apply, check_transform
from fleetmap.matching import MatchParams, match_descriptors_at, verify_pair

ALIGN_FEATURES = FeatureParams(max_features=1000, min_mser_features=400)
ALIGN_MATCH = MatchParams(ratio=0.85, min_epipolar_inliers=8, min_inlier_ratio=0.0)
_VIEWS = Recent(256)  # at most 1,000 features (136 kB) a view: 35 MB


@dataclass
class RGBDView:
    """One keyframe: colour (H, W, 3) uint8, depth (H, W) uint16, intrinsics, pose."""

    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    T_map_cam: np.ndarray
    stamp: float = 0.0

    def __post_init__(self) -> None:
        if self.rgb.dtype != np.uint8 or self.rgb.ndim not in (2, 3):
            raise BadInput(
                f"Expected colour uint8 (H, W[, 3]), got {self.rgb.dtype} {self.rgb.shape}"
            )
        if self.depth.dtype != np.uint16 or self.depth.ndim != 2:
            raise BadInput(
                f"Expected depth uint16 (H, W), got {self.depth.dtype} {self.depth.shape}"
            )
        if self.depth.shape != self.rgb.shape[:2]:
            raise BadInput(
                f"Depth of shape {self.depth.shape} does not match colour {self.rgb.shape[:2]}"
            )
        if not np.any(self.depth):
            raise NoDepthReading("Depth image has no valid reading")
        self.T_map_cam = check_transform(self.T_map_cam, "T_map_cam")


@dataclass
class Correspondences:
    """Matched points: X (N, 3) in robot B's map, Y (N, 3) in robot A's, pair index (N,)."""

    X: np.ndarray
    Y: np.ndarray
    pair: np.ndarray

    def __len__(self) -> int:
        return len(self.X)

    @staticmethod
    def concat(parts: list[Correspondences]) -> Correspondences:
        if not parts:
            return Correspondences(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int))
        return Correspondences(
            np.concatenate([p.X for p in parts]),
            np.concatenate([p.Y for p in parts]),
            np.concatenate([p.pair for p in parts]),
        )


def view_features(view: RGBDView, params: FeatureParams = ALIGN_FEATURES) -> LocalFeatures:
    """A view's MSER + SIFT at the aligner's settings (kept by `fleetmap.feature_cache`
    where one is on, and in memory for the last few hundred views: `Recent`)."""
    detect = partial(detect_and_describe, view.rgb, params)
    key = (digest(view.rgb), params)
    return _VIEWS.get(key, lambda: cached_local(view.rgb, detect, params, "aligner view"))


def pair_correspondences(
    a: RGBDView,
    b: RGBDView,
    index: int = 0,
    fa: LocalFeatures | None = None,
    fb: LocalFeatures | None = None,
    match: MatchParams = ALIGN_MATCH,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> Correspondences:
    """3D-3D correspondences of one pair (view a of robot A, view b of robot B), verified
    by the epipolar RANSAC; `matches` at `match.ratio` when already computed."""
    fa = fa or view_features(a)
    fb = fb or view_features(b)
    v = verify_pair(
        fa.keypoints, fa.descriptors, fb.keypoints, fb.descriptors, match, matches=matches
    )
    if v.inliers == 0:
        return Correspondences.concat([])
    return lift(a, b, fa, fb, v.idx_a, v.idx_b, index)


def lift(a, b, fa, fb, ia, ib, index: int) -> Correspondences:
    """Matched features with depth on both sides, each into its robot's map frame."""
    pa, va = backproject_pixels(fa.keypoints[ia], a.depth, a.intrinsics)
    pb, vb = backproject_pixels(fb.keypoints[ib], b.depth, b.intrinsics)
    ok = va & vb
    return Correspondences(
        apply(b.T_map_cam, pb[ok]), apply(a.T_map_cam, pa[ok]), np.full(int(ok.sum()), index)
    )


def pair_features(pairs: list[tuple[RGBDView, RGBDView]]) -> dict[int, LocalFeatures]:
    """Features of every distinct view (the same object in several pairs counts once), by
    id(view); two threads, as OpenCV releases the GIL (1.5x on 2 cores)."""
    from concurrent.futures import ThreadPoolExecutor

    distinct = list({id(v): v for pr in pairs for v in pr}.values())
    with ThreadPoolExecutor(2) as ex:
        return dict(zip(map(id, distinct), ex.map(view_features, distinct), strict=True))


def pooled_correspondences(
    pairs: list[tuple[RGBDView, RGBDView]], feats: dict[int, LocalFeatures] | None = None
) -> Correspondences:
    """Verified correspondences of several pairs; `feats` from `pair_features`."""
    f = feats if feats is not None else pair_features(pairs)
    return Correspondences.concat(
        [pair_correspondences(a, b, i, f[id(a)], f[id(b)]) for i, (a, b) in enumerate(pairs)]
    )


def verified_and_raw(
    pairs: list[tuple[RGBDView, RGBDView]], feats: dict[int, LocalFeatures], ratio: float = 0.9
) -> tuple[Correspondences, Correspondences]:
    """`pooled_correspondences` and every pair's raw matches (mutual ratio-test matches
    lifted to 3D, no epipolar filter), from one descriptor matching per pair.

    Across wide baselines (robots 60-90 degrees apart) the epipolar RANSAC keeps too few
    right matches; a rigid RANSAC in 3D on the raw matches, judged by geometry, does
    better (see `fleetmap.align`).

    Two threads, one pair each: numpy's product and OpenCV's USAC release the GIL, and a
    pair's inliers do not depend on the thread (the same correspondences to the bit over
    four replays). SUN3D's 120 view pairs 0.50 -> 0.28 s (docs/BENCHMARKS.md, session 42)."""
    from concurrent.futures import ThreadPoolExecutor

    def one(k: int) -> tuple[Correspondences, Correspondences]:
        a, b = pairs[k]
        fa, fb = feats[id(a)], feats[id(b)]
        verify, raw = match_descriptors_at(
            fa.descriptors, fb.descriptors, (ALIGN_MATCH.ratio, ratio)
        )
        return pair_correspondences(a, b, k, fa, fb, matches=verify), lift(a, b, fa, fb, *raw, k)

    with ThreadPoolExecutor(2) as ex:
        found = list(ex.map(one, range(len(pairs))))
    return Correspondences.concat([v for v, _ in found]), Correspondences.concat(
        [r for _, r in found]
    )
