"""Alignment of two robots' maps from RGB-D pairs: real data, known transforms."""

import numpy as np
import pytest

from fleetmap.align import AlignParams, align_views
from fleetmap.camera import TUM_FR1
from fleetmap.correspondences import RGBDView, pooled_correspondences
from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.errors import BadInput
from fleetmap.extract import keyframe_indices
from fleetmap.geometry import transform_error
from tests.conftest import imread, read_tum_pose


def test_recovers_a_known_transform_from_a_real_rgbd_pair(tum_two_robots):
    pairs, T_a_b = tum_two_robots
    res = align_views(pairs)
    assert res.merged, res.reason
    dt, dr = transform_error(res.T_a_b, T_a_b)
    assert dt < 0.05 and dr < 2.0
    assert res.inliers >= 50 and res.holdout_m < 0.03


def test_correspondences_land_on_the_same_world_points(tum_two_robots):
    pairs, T_a_b = tum_two_robots
    C = pooled_correspondences(pairs)
    err = np.linalg.norm(C.X @ T_a_b[:3, :3].T + T_a_b[:3, 3] - C.Y, axis=1)
    assert len(C) > 50 and np.median(err) < 0.03


def sun3d_keyframes(sun3d, robot: str) -> list[RGBDView]:
    rec = read_recording(sun3d / robot)
    return [
        RGBDView(
            load_rgb(f.rgb_path), load_depth(f.depth_path), rec.intrinsics, f.T_map_cam, f.stamp
        )
        for f in (rec.frames[i] for i in keyframe_indices(rec))
    ]


def test_sun3d_wide_baseline_recovers_the_ground_truth(sun3d):
    """Self-similar study room seen 60-90 degrees apart: the largest visual consensus is a
    look-alike cubicle 0.9 m away; per-pair hypotheses judged by free space find the right
    one, and a rival is reported."""
    T_gt = np.loadtxt(sun3d / "T_a_b.txt")
    va, vb = sun3d_keyframes(sun3d, "robot_a"), sun3d_keyframes(sun3d, "robot_b")
    res = align_views([(a, b) for a in va for b in vb])
    assert res.merged, res.reason
    dt, dr = transform_error(res.T_a_b, T_gt)
    assert dt < 0.05 and dr < 2.0, (dt, dr, res.to_dict())
    assert res.hypotheses[0]["consistency"] > 0.7
    assert any(h["score"] < 0.8 * res.hypotheses[0]["score"] for h in res.hypotheses[1:])


def test_different_places_are_not_merged(sun3d, tum_pairs):
    """The study room against a TUM office desk: no pair of them overlaps."""
    va = sun3d_keyframes(sun3d, "robot_a")
    vb = []
    for case in sorted(tum_pairs.glob("case_*")):
        for k in ("prev", "curr"):
            vb.append(
                RGBDView(
                    imread(case / f"img_{k}.png"),
                    imread(case / f"dep_{k}.png"),
                    TUM_FR1,
                    read_tum_pose(case / f"pose_{k}.txt"),
                )
            )
    res = align_views([(a, b) for a in va for b in vb])
    assert not res.merged and res.reason, res.to_dict()
    # the desk's few frames laid on the room's planes fit at 0.95 consistency on half the
    # desk, but cover a few % of the room: the geometry does not decide on its own
    assert "need 6" not in res.reason, res.reason


def test_gate_refuses_too_few_correspondences(tum_two_robots):
    pairs, _ = tum_two_robots
    res = align_views(pairs, AlignParams(min_inliers=10_000))
    assert not res.merged and "correspondences" in res.reason


def test_bad_views_are_named():
    rgb = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(BadInput, match="does not match colour"):
        RGBDView(rgb, np.ones((40, 64), np.uint16), TUM_FR1, np.eye(4))
    with pytest.raises(BadInput, match="no valid reading"):
        RGBDView(rgb, np.zeros((48, 64), np.uint16), TUM_FR1, np.eye(4))
    with pytest.raises(BadInput, match="uint16"):
        RGBDView(rgb, np.ones((48, 64), np.float32), TUM_FR1, np.eye(4))
    with pytest.raises(BadInput, match="at least one"):
        align_views([])


@pytest.mark.parametrize(
    "part_a, part_b, swap",
    [
        (slice(None), slice(0, 7), False),
        (slice(None), slice(7, None), False),  # once merged 0.77 m off: the free-space gate
        (slice(0, 5), slice(None), False),
        (slice(5, None), slice(None), False),
        (slice(None), slice(None), True),
    ],
)
def test_sun3d_parts_are_merged_right_or_not_at_all(sun3d, part_a, part_b, swap):
    """Less overlap (parts of either robot) or the robots' roles swapped: the answer is
    near the ground truth (15 cm / 3 deg, i.e. not a look-alike place) or no merge."""
    T_gt = np.loadtxt(sun3d / "T_a_b.txt")
    va = sun3d_keyframes(sun3d, "robot_a")[part_a]
    vb = sun3d_keyframes(sun3d, "robot_b")[part_b]
    if swap:
        va, vb, T_gt = vb, va, np.linalg.inv(T_gt)
    res = align_views([(a, b) for a in va for b in vb])
    if res.merged:
        dt, dr = transform_error(res.T_a_b, T_gt)
        assert dt < 0.15 and dr < 3.0, (dt, dr, res.to_dict())
    else:
        assert res.reason


def test_surface_rmse_prefers_the_truth_to_a_slide(hololens):
    """The refinement choice measures on depth alone: on real HoloLens maps, the true
    alignment's surfaces sit closer than the same alignment slid 3 cm along any axis."""
    from fleetmap.align import surface_rmse
    from fleetmap.dataset import read_recording
    from fleetmap.mapcloud import views_cloud
    from fleetmap.pairs import load_view

    clouds = []
    for name in ("hl_a", "hl_b"):
        rec = read_recording(hololens / name)
        clouds.append(views_cloud([load_view(rec, i) for i in range(0, len(rec), 3)], voxel=0.03))
    T = np.loadtxt(hololens / "T_a_b.txt")
    best = surface_rmse(clouds[1], clouds[0], T, 0.045)
    for axis in range(3):
        slid = T.copy()
        slid[axis, 3] += 0.03
        assert surface_rmse(clouds[1], clouds[0], slid, 0.045) > best
