"""From an RGB-D keyframe to its frame structure (thesis eq. 2.7): one pipeline stage."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from fleetmap.camera import Intrinsics, backproject_pixels
from fleetmap.dataset import Recording
from fleetmap.errors import BadInput
from fleetmap.feature_cache import FeatureCache, cached, salt_of
from fleetmap.features import DEFAULT_PARAMS as FEATURE_DEFAULTS
from fleetmap.features import FeatureParams, detect_and_describe
from fleetmap.frame import Frame
from fleetmap.geometry import apply
from fleetmap.gist import compute_gist
from fleetmap.keyframes import KeyframePolicy, select_keyframes
from fleetmap.vocabulary import Vocabulary

log = logging.getLogger(__name__)

#: A keyframe's features that depend on its colour image alone (`FrameExtractor.image_features`)
IMAGE_FIELDS = ("gist", "keypoints", "descriptors", "bow_ids", "bow_counts")


@dataclass
class FrameExtractor:
    """Computes frame structures with one vocabulary and one set of detector settings."""

    vocabulary: Vocabulary
    feature_params: FeatureParams = field(default_factory=lambda: FEATURE_DEFAULTS)
    #: features kept by image (`fleetmap.feature_cache`); default `$FLEETMAP_FEATURE_CACHE`
    cache: FeatureCache | None = None

    def __post_init__(self) -> None:
        if self.cache is None:
            salt = salt_of(
                self.feature_params, self.vocabulary.gist_params, self.vocabulary.vocab_id
            )
            self.cache = FeatureCache.from_env(salt)

    def image_features(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """GIST (float16), keypoints, descriptors and bag of words of a colour image: from
        the cache where it holds them, else computed (and kept there)."""

        def make() -> dict:
            local = detect_and_describe(rgb, self.feature_params)
            ids, counts = self.vocabulary.bow(local.descriptors)
            gist = compute_gist(rgb, self.vocabulary.gist_params).astype(np.float16)
            arrays = (gist, local.keypoints, local.descriptors, ids, counts)
            return dict(zip(IMAGE_FIELDS, arrays, strict=True))

        return cached(self.cache, rgb, IMAGE_FIELDS, make)

    def __call__(
        self,
        robot_id: str,
        stamp: float,
        rgb: np.ndarray,
        depth: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
        T_map_cam: np.ndarray | None = None,
    ) -> Frame:
        """Frame structure of one keyframe.

        Parameters
        ----------
        rgb : ndarray of shape (H, W, 3) uint8 BGR (or (H, W) grey).
        depth : ndarray of shape (H, W) uint16, or None. With depth, `intrinsics` and
            `T_map_cam`, each feature gets its 3D point in the robot's map frame.
        T_map_cam : ndarray of shape (4, 4), camera-to-map pose, or None.
        """
        if rgb.ndim not in (2, 3):
            raise BadInput(f"Expected an image of shape (H, W[, 3]), got {rgb.shape}")
        h, w = rgb.shape[:2]
        f = self.image_features(rgb)
        points = valid = None
        if depth is not None and intrinsics is not None and T_map_cam is not None:
            if depth.shape != (h, w):
                raise BadInput(f"Depth of shape {depth.shape} does not match colour {(h, w)}")
            p_cam, valid = backproject_pixels(f["keypoints"], depth, intrinsics)
            points = np.where(valid[:, None], apply(T_map_cam, p_cam), 0.0).astype(np.float32)
        return Frame(
            robot_id=robot_id,
            stamp=stamp,
            gist=f["gist"],
            keypoints=f["keypoints"],
            descriptors=f["descriptors"],
            bow_ids=f["bow_ids"],
            bow_counts=f["bow_counts"],
            T_map_cam=T_map_cam,
            points=points,
            point_valid=valid,
            width=w,
            height=h,
            vocab_id=self.vocabulary.vocab_id,
            intrinsics=intrinsics,
        )


def keyframe_indices(rec: Recording, policy: KeyframePolicy | None = None) -> list[int]:
    """Indices into `rec.frames` of the recording's keyframes."""
    return select_keyframes(
        [f.stamp for f in rec.frames], [f.T_map_cam for f in rec.frames], policy
    )


def extract_recording(
    rec: Recording, extractor: FrameExtractor, policy: KeyframePolicy | None = None
) -> Iterator[Frame]:
    """Frame structures of a recording's keyframes, in time order (lazy: one image pair
    is in memory at a time)."""
    for i in keyframe_indices(rec, policy):
        rec_frame = rec.frames[i]
        rgb = rec.rgb(rec_frame)
        depth = rec.depth(rec_frame) if rec_frame.depth_path else None
        yield extractor(
            rec.robot_id, rec_frame.stamp, rgb, depth, rec.intrinsics, rec_frame.T_map_cam
        )
