import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from fleetmap.camera import TUM_FR1, Intrinsics, backproject_pixels, depth_to_points
from fleetmap.errors import BadInput, BadRobotData
from fleetmap.geometry import apply, invert
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


def test_the_edge_window_repeats_the_border_as_padding_the_image_did():
    """`backproject_pixels` reads each pixel's 3x3 window by clipped indices instead of a
    padded copy of the whole image (session 24): the same points and validity as the
    padded definition, on pixels at the borders and corners, near holes and off the image."""
    rng = np.random.default_rng(0)
    for smooth in (False, True):
        depth = rng.integers(0, 20_000, (48, 64)).astype(np.uint16)
        if smooth:  # a wall at 1 m: edges decided by a few readings of noise and the holes
            depth = (5000 + rng.integers(0, 30, (48, 64))).astype(np.uint16)
        depth[rng.random((48, 64)) < 0.1] = 0
        uv = np.c_[rng.uniform(-3, 67, 3000), rng.uniform(-3, 51, 3000)]
        uv[:4] = [[0, 0], [63, 47], [0, 47], [63, 0]]
        pts, valid = backproject_pixels(uv, depth, TUM_FR1)
        u = np.clip(np.round(uv[:, 0]).astype(int), 0, 63)
        v = np.clip(np.round(uv[:, 1]).astype(int), 0, 47)
        pad = np.pad(depth.astype(np.float64), 1, mode="edge") / TUM_FR1.depth_scale
        win = np.stack([pad[v + dy, u + dx] for dy in range(3) for dx in range(3)], axis=1)
        z = depth[v, u] / TUM_FR1.depth_scale
        spread = win.max(1) - np.where(win > 0, win, np.inf).min(1)
        want = (z > 0) & (z < 8) & (win > 0).all(1) & (spread <= 0.05 * np.maximum(z, 1e-6))
        np.testing.assert_array_equal(valid, want)
        assert not valid.all() and (valid.any() or not smooth)  # the wall: some of each
        np.testing.assert_array_equal(pts[:, 2], np.where(want, z, 0.0))


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


def _write_camera(tmp_path, content) -> Path:
    path = tmp_path / "camera.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


def test_camera_json_in_open3d_format(tmp_path):
    """Open3D's own PinholeCameraIntrinsic file plus depth_scale (a RealSense user's)."""
    import open3d as o3d

    path = tmp_path / "camera.json"
    cam = o3d.camera.PinholeCameraIntrinsic(848, 480, 421.5, 421.0, 424.1, 239.2)
    o3d.io.write_pinhole_camera_intrinsic(str(path), cam)
    d = json.loads(path.read_text())
    d["depth_scale"] = 1000.0
    path.write_text(json.dumps(d))
    intr = Intrinsics.from_json_file(path)
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (421.5, 421.0, 424.1, 239.2)
    assert (intr.width, intr.height, intr.depth_scale) == (848, 480, 1000.0)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (
            {
                "width": 848,
                "height": 480,
                "intrinsic_matrix": [421.5, 0, 0, 0, 421, 0, 424, 239, 1],
            },
            r"missing \['depth_scale'\]",
        ),
        ({"fx": 600.0}, r"missing \['cx', 'cy', 'depth_scale', 'fy', 'height', 'width'\]"),
        ({**TUM_FR1.to_dict(), "k1": 0.1}, r"unknown \['k1'\]"),
        ({**TUM_FR1.to_dict(), "fx": True}, "fx must be a number"),
        ({**TUM_FR1.to_dict(), "width": 640.5}, "width must be a whole number"),
        (
            {"width": 640, "height": 480, "intrinsic_matrix": [1, 2], "depth_scale": 1000},
            "9 numbers",
        ),
        ([1, 2], "expected a JSON object"),
        ("{not json", "Cannot read camera file"),
    ],
)
def test_camera_json_mistakes_are_errors_not_defaults(tmp_path, content, message):
    with pytest.raises(BadRobotData, match=message):
        Intrinsics.from_json_file(_write_camera(tmp_path, content))


@pytest.mark.parametrize("d", [[1, 2], {}, {"fx": 500.0}, {**TUM_FR1.to_dict(), "extra": 1}])
def test_intrinsics_payloads_must_be_complete(d):
    with pytest.raises(BadInput, match="Intrinsics"):
        Intrinsics.from_dict(d)
