import numpy as np
import pytest

from fleetmap.camera import TUM_FR1
from fleetmap.dataset import associate, load_depth, parse_robot_arg, read_recording
from fleetmap.errors import BadRobotData


def test_reads_sun3d_robot_with_camera_json(sun3d):
    rec = read_recording(sun3d / "robot_a")
    assert rec.robot_id == "robot_a"
    assert len(rec) == 50
    assert rec.intrinsics.fx == pytest.approx(570.342205)
    assert rec.intrinsics.depth_scale == 1000.0
    stamps = [f.stamp for f in rec.frames]
    assert stamps == sorted(stamps)
    T = rec.frames[0].T_map_cam
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], [5.018527, -2.335860, 3.321476])


def test_tum_folder_without_camera_json_uses_fr1_defaults(tum_robot):
    rec = read_recording(tum_robot, robot_id="scout")
    assert rec.robot_id == "scout"
    assert rec.intrinsics == TUM_FR1
    assert len(rec) == 2  # depth stamps are 4 ms off: within the 20 ms association gap
    assert load_depth(rec.frames[0].depth_path).dtype == np.uint16


def test_association_is_nearest_one_to_one_within_gap():
    a = np.array([0.0, 0.033, 0.066, 1.0])
    b = np.array([0.001, 0.030, 0.070, 0.5])
    assert associate(a, b, 0.02) == [(0, 0), (1, 1), (2, 2)]


def test_frames_without_depth_partner_are_dropped(tum_robot):
    lines = (tum_robot / "depth.txt").read_text().splitlines()
    (tum_robot / "depth.txt").write_text("\n".join(lines[:-1]) + "\n")
    assert len(read_recording(tum_robot)) == 1


@pytest.mark.parametrize("missing", ["rgb.txt", "depth.txt", "groundtruth.txt"])
def test_missing_list_file_is_named(tum_robot, missing):
    (tum_robot / missing).unlink()
    kwargs = {"require_depth": True, "require_poses": True}
    with pytest.raises(BadRobotData, match=missing):
        read_recording(tum_robot, **kwargs)


def test_missing_folder_and_bad_pose_are_clear(tum_robot, tmp_path):
    with pytest.raises(BadRobotData, match="not found"):
        read_recording(tmp_path / "nope")
    (tum_robot / "groundtruth.txt").write_text("1305031102.2159 1 2 3 0 0 0\n")
    with pytest.raises(BadRobotData, match="expected 'timestamp tx ty tz qx qy qz qw'"):
        read_recording(tum_robot)


def test_list_entries_cannot_escape_the_folder(tum_robot):
    (tum_robot / "rgb.txt").write_text("1305031102.2159 ../../etc/passwd\n")
    with pytest.raises(BadRobotData, match="outside the robot folder"):
        read_recording(tum_robot)


def test_unreadable_depth_image_is_named(tum_robot):
    bad = tum_robot / "depth" / "broken.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(BadRobotData, match="broken.png"):
        load_depth(bad)


def test_parse_robot_arg(tmp_path):
    assert parse_robot_arg(f"alpha={tmp_path}") == ("alpha", tmp_path)
    assert parse_robot_arg(str(tmp_path)) == (None, tmp_path)
