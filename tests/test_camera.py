import cv2
import numpy as np
import pytest

from shared.camera import TUM_FR1, Intrinsics, backproject_pixels, depth_to_points
from shared.errors import BadInput, BadRobotData
from shared.geometry import apply, invert
from tests.conftest import imread, read_tum_pose


def test_backprojection_agrees_with_ground_truth_poses(tum_pairs):
    """Features of two real fr1 frames, lifted through depth, intrinsics and the mocap
    poses, land on the same world points (the data README: ~4 mm median depth agreement)."""
    case = tum_pairs / "case_1"
    prev_img, curr_img = imread(case / "img_prev.png"), imread(case / "img_curr.png")
    prev_d, curr_d = imread(case / "dep_prev.png"), imread(case / "dep_curr.png")
    T_w_prev, T_w_curr = (
        read_tum_pose(case / "pose_prev.txt"),
        read_tum_pose(case / "pose_curr.txt"),
    )
    sift = cv2.SIFT_create(800)
    ka, da = sift.detectAndCompute(cv2.cvtColor(prev_img, cv2.COLOR_BGR2GRAY), None)
    kb, db = sift.detectAndCompute(cv2.cvtColor(curr_img, cv2.COLOR_BGR2GRAY), None)
    good = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.7 * n.distance]
    ua = np.array([ka[m.queryIdx].pt for m in good])
    ub = np.array([kb[m.trainIdx].pt for m in good])
    pa, va = backproject_pixels(ua, prev_d, TUM_FR1)
    pb, vb = backproject_pixels(ub, curr_d, TUM_FR1)
    ok = va & vb
    assert ok.sum() > 50
    err = np.linalg.norm(apply(T_w_prev, pa[ok]) - apply(T_w_curr, pb[ok]), axis=1)
    assert np.median(err) < 0.03


def test_depth_edges_and_holes_are_rejected():
    depth = np.full((50, 50), 5000, np.uint16)
    depth[:, 25:] = 15000  # a 2 m jump
    depth[10, 10] = 0
    pts, valid = backproject_pixels(
        np.array([[5, 5], [24, 30], [10, 10], [40, 40]]), depth, Intrinsics(width=50, height=50)
    )
    assert valid.tolist() == [True, False, False, True]
    assert pts[0, 2] == pytest.approx(1.0) and pts[3, 2] == pytest.approx(3.0)


def test_dense_points_and_round_trip_through_a_pose():
    depth = np.full((48, 64), 10000, np.uint16)
    intr = Intrinsics(fx=50, fy=50, cx=32, cy=24, width=64, height=48)
    pts, uv = depth_to_points(depth, intr, stride=4)
    assert pts.shape == (12 * 16, 3) and np.allclose(pts[:, 2], 2.0)
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(apply(invert(T), apply(T, pts)), pts, atol=1e-12)


def test_bad_intrinsics(tmp_path):
    with pytest.raises(BadInput, match="finite and positive"):
        Intrinsics(fx=-1)
    (tmp_path / "camera.json").write_text("{not json")
    with pytest.raises(BadRobotData, match="camera.json"):
        Intrinsics.from_json_file(tmp_path / "camera.json")
