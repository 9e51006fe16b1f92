import cv2
import numpy as np
import pytest

from fleetmap.errors import BadInput
from fleetmap.features import FeatureParams, detect_and_describe
from tests.conftest import imread


def test_capped_uint8_and_inside_image(sun3d):
    img = imread(sorted((sun3d / "robot_a" / "rgb").glob("*.png"))[0])
    lf = detect_and_describe(img, FeatureParams(max_features=200))
    assert 100 <= len(lf) <= 200
    assert lf.descriptors.dtype == np.uint8 and lf.descriptors.shape == (len(lf), 128)
    assert lf.keypoints.dtype == np.float32
    h, w = img.shape[:2]
    assert np.all((lf.keypoints >= 0) & (lf.keypoints < [w, h]))


def test_features_match_across_a_real_viewpoint_change(tum_pairs):
    """Two fr1_xyz frames 60 ms apart: many matches survive the ratio test and RANSAC."""
    a = detect_and_describe(imread(tum_pairs / "case_1" / "img_prev.png"))
    b = detect_and_describe(imread(tum_pairs / "case_1" / "img_curr.png"))
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(
        a.descriptors.astype(np.float32), b.descriptors.astype(np.float32), k=2
    )
    good = [m for m, n in matches if m.distance < 0.8 * n.distance]
    pa = a.keypoints[[m.queryIdx for m in good]]
    pb = b.keypoints[[m.trainIdx for m in good]]
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, 1.0, 0.999)
    assert mask is not None and mask.sum() >= 40


def test_sift_tops_up_where_mser_finds_too_few():
    """A smooth image with a few corner blobs: MSER finds little, SIFT fills in."""
    rng = np.random.default_rng(1)
    img = np.tile(np.linspace(60, 200, 320, dtype=np.uint8), (240, 1))
    for _ in range(40):
        x, y = rng.integers(10, 300), rng.integers(10, 220)
        cv2.circle(img, (int(x), int(y)), int(rng.integers(2, 6)), int(rng.integers(0, 255)), -1)
    mser_only = detect_and_describe(img, FeatureParams(min_mser_features=0))
    topped = detect_and_describe(img, FeatureParams(min_mser_features=100))
    assert len(topped) > len(mser_only)


def test_blank_image_gives_no_features_and_bad_dtype_is_rejected():
    assert len(detect_and_describe(np.full((240, 320), 128, np.uint8))) == 0
    with pytest.raises(BadInput, match="uint8"):
        detect_and_describe(np.zeros((240, 320), np.float32))


def test_verification_treats_an_estimator_failure_as_unverified(monkeypatch):
    """OpenCV's USAC asserts on some degenerate samples (seen on a simulated 8-robot fleet):
    that must mean "not verified", never an exception out of a query or the worker."""
    from fleetmap import matching

    def boom(*args, **kwargs):
        raise cv2.error("OpenCV(5.0.0) error: (-215:Assertion failed) !model.empty()")

    monkeypatch.setattr(matching.cv2, "findFundamentalMat", boom)
    rng = np.random.default_rng(0)
    desc = rng.integers(0, 255, (40, 128)).astype(np.uint8)
    kp = rng.uniform(0, 300, (40, 2)).astype(np.float32)
    v = matching.verify_pair(kp, desc, kp, desc)
    assert v.matches == 40 and not v.verified and v.inliers == 0
