"""Robots given as ROS bags: built here with `rosbags` from real recordings, read back to
the same frames, poses and intrinsics as the folder, and merged to the same transform."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from fleetmap.bags import BagTopics, bag_to_tum, is_bag
from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.errors import BadRobotData
from fleetmap.geometry import pose_to_tum, transform_error

rosbags = pytest.importorskip("rosbags")


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    """Converted bags go to a cache folder of the test's own."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def write_bag(
    robot_dir,
    bag,
    ros1: bool = False,
    depth_m: bool = False,
    frames=None,
    zero_stamps=False,
    packed: str | None = None,
    k_zero: int = 0,
    info: bool = True,
    k_times: float = 1.0,
) -> None:
    """A robot folder as a bag: colour (rgb8), depth (16UC1 mm or 32FC1 m), CameraInfo and
    PoseStamped, each message stamped with its frame's time (`zero_stamps`: every header's
    stamp 0, as a driver without a clock writes them; the bag's record times still differ).
    `packed` ("png", "jpeg"): colour as image_transport's CompressedImage in that format.
    `k_zero`: the first k_zero CameraInfo messages' K all zeros (an uncalibrated driver);
    `info`: False, no CameraInfo topic; `k_times`: K scaled (0.007: a focal length in mm)."""
    from rosbags.typesys import Stores, get_typestore

    rec = read_recording(robot_dir)
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Image, Info = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"]
    Packed = T["sensor_msgs/msg/CompressedImage"]
    Pose, PoseStamped = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/PoseStamped"]
    Point, Quat = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    K = rec.intrinsics
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(bag), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(bag, version=9), ts.serialize_cdr

    def header(stamp: float):
        stamp = 0.0 if zero_stamps else stamp
        sec = int(stamp)
        kw = {"seq": 0} if ros1 else {}
        return Header(**kw, stamp=Time(sec=sec, nanosec=round((stamp - sec) * 1e9)), frame_id="c")

    def image(stamp, arr, enc):
        h, w = arr.shape[:2]
        data = np.ascontiguousarray(arr).view(np.uint8).reshape(-1)
        return Image(header(stamp), h, w, enc, 0, data.size // h, data)

    with writer:
        colour_type = (Packed if packed else Image).__msgtype__
        c_rgb = writer.add_connection("/cam/color", colour_type, typestore=ts)
        c_depth = writer.add_connection("/cam/depth", Image.__msgtype__, typestore=ts)
        c_info = info and writer.add_connection("/cam/info", Info.__msgtype__, typestore=ts)
        c_pose = writer.add_connection("/cam/pose", PoseStamped.__msgtype__, typestore=ts)
        for n, f in enumerate(rec.frames[:frames]):
            ns = round(f.stamp * 1e9)
            rgb = load_rgb(f.rgb_path)[:, :, ::-1]
            depth = load_depth(f.depth_path)
            if depth_m:
                depth = np.where(depth > 0, depth / K.depth_scale, np.nan).astype("<f4")
            dmsg = image(f.stamp, depth, "32FC1" if depth_m else "16UC1")
            kw = dict(
                height=K.height,
                width=K.width,
                distortion_model="plumb_bob",
                d=np.zeros(5),
                k=np.array([K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1.0]) * (n >= k_zero) * k_times,
                r=np.eye(3).ravel(),
                p=np.zeros(12),
                binning_x=0,
                binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False),
            )
            if ros1:
                kw = {k.upper() if k in "krpd" else k: v for k, v in kw.items()}
            msg_info = Info(header=header(f.stamp), **kw)
            p = pose_to_tum(f.T_map_cam)
            pose = PoseStamped(header(f.stamp), Pose(Point(*p[:3]), Quat(*p[3:])))
            if packed:
                data = cv2.imencode(f".{packed}", rgb[:, :, ::-1])[1].reshape(-1)
                cmsg = Packed(header(f.stamp), f"rgb8; {packed} compressed bgr8", data)
                writer.write(c_rgb, ns, ser(cmsg, colour_type))
            else:
                writer.write(c_rgb, ns, ser(image(f.stamp, rgb, "rgb8"), Image.__msgtype__))
            writer.write(c_depth, ns, ser(dmsg, Image.__msgtype__))
            if c_info:
                writer.write(c_info, ns, ser(msg_info, Info.__msgtype__))
            writer.write(c_pose, ns, ser(pose, PoseStamped.__msgtype__))


@pytest.mark.parametrize(("ros1", "packed"), [(False, None), (True, None), (False, "png")])
def test_a_bag_reads_as_the_folder_it_was_made_from(sun3d, tmp_path, ros1, packed):
    """`packed`: colour as CompressedImage, as most bags hold it (it was "colour image
    topics []": session 59's outside tester)."""
    folder = sun3d / "robot_b"
    bag = tmp_path / ("b.bag" if ros1 else "b_bag")
    write_bag(folder, bag, ros1=ros1, frames=6, packed=packed)
    assert is_bag(bag)
    rec_bag = read_recording(bag, topics=BagTopics())
    rec_dir = read_recording(folder)
    assert rec_bag.robot_id == "b" if ros1 else "b_bag"
    assert rec_bag.intrinsics == rec_dir.intrinsics
    assert len(rec_bag) == 6
    for fb, fd in zip(rec_bag.frames, rec_dir.frames[:6], strict=True):
        assert abs(fb.stamp - fd.stamp) < 1e-6
        np.testing.assert_allclose(fb.T_map_cam, fd.T_map_cam, atol=1e-6)
        np.testing.assert_array_equal(load_rgb(fb.rgb_path), load_rgb(fd.rgb_path))
        np.testing.assert_array_equal(load_depth(fb.depth_path), load_depth(fd.depth_path))


def test_a_ros2_bag_rewritten_in_place_is_converted_again(sun3d, tmp_path):
    """The conversion was cached by the bag folder's own size and time, which rewriting its
    .db3 and metadata.yaml in place changes neither: the 6-frame conversion was read for
    the 3-frame bag (an outside tester's review)."""
    import shutil

    bag, other = tmp_path / "b_bag", tmp_path / "other" / "b_bag"
    write_bag(sun3d / "robot_b", bag, frames=6)
    assert len(read_recording(bag)) == 6
    write_bag(sun3d / "robot_b", other, frames=3)
    names = sorted(p.name for p in bag.iterdir())
    assert names == sorted(p.name for p in other.iterdir())  # the same files, rewritten
    for name in names:
        shutil.copyfile(other / name, bag / name)
    assert len(read_recording(bag)) == 3


def test_depth_in_metres_and_ambiguous_topics(sun3d, tmp_path):
    bag = tmp_path / "m_bag"
    write_bag(sun3d / "robot_a", bag, depth_m=True, frames=2)
    out = bag_to_tum(bag, tmp_path / "tum")
    d = load_depth(sorted((out / "depth").glob("*.png"))[0])
    ref = load_depth(read_recording(sun3d / "robot_a").frames[0].depth_path)
    assert np.abs(d.astype(int) - ref.astype(int)).max() <= 1  # millimetres, rounded
    with pytest.raises(BadRobotData, match="no topic '/nope'"):
        bag_to_tum(bag, tmp_path / "x", BagTopics(pose="/nope"))


@pytest.mark.slow
def test_merge_with_a_ros2_bag_robot_gives_the_folder_transform(sun3d, sun3d_merge, tmp_path):
    """The issue's target: within 1 mm of the same recording given as a folder (the
    session's merge of the folders, `sun3d_merge`)."""
    from fleetmap.services.cli import main

    bag = tmp_path / "robot_b_bag"
    write_bag(sun3d / "robot_b", bag)
    out_bag = tmp_path / "with_bag"
    a = f"A={sun3d / 'robot_a'}"
    assert main(["-q", "merge", a, f"B={bag}", "-o", str(out_bag)]) == 0
    report = json.loads((out_bag / "report.json").read_text())
    T_bag = np.array(report["transforms"]["B"])
    assert report["robots"]["B"]["source"] == str(bag)  # the bag given, not its cache folder
    T_dir = np.array(sun3d_merge[1]["transforms"]["B"])
    dt, dr = transform_error(T_bag, T_dir)
    assert dt < 0.001 and dr < 0.05, (dt, dr)


def test_convert_writes_a_tum_folder(sun3d, tmp_path, capsys):
    from fleetmap.services.cli import main

    bag = tmp_path / "b_bag"
    write_bag(sun3d / "robot_b", bag, frames=3)
    assert main(["convert", str(bag), "-o", str(tmp_path / "tum")]) == 0
    assert "3 RGB-D frames with poses" in capsys.readouterr().out
    rec = read_recording(tmp_path / "tum")
    assert rec.intrinsics == read_recording(sun3d / "robot_b").intrinsics and len(rec) == 3
    assert main(["convert", str(sun3d / "robot_b"), "-o", str(tmp_path / "x")]) == 1
    assert "not a ROS bag" in capsys.readouterr().err


def test_a_convert_that_fails_names_why_and_leaves_nothing(sun3d, tmp_path, capsys):
    """Each was a traceback or a silent wrong result before (an outside tester's review,
    session 51): a topic of another type given for the poses (an AttributeError), header
    stamps all equal (every image written over one file, 'converted' with the wrong
    poses), and a failed convert's folder left behind, which refused the retry."""
    from fleetmap.services.cli import main

    bag = tmp_path / "b_bag"
    write_bag(sun3d / "robot_b", bag, frames=3)
    out = tmp_path / "tum"
    assert main(["convert", str(bag), "-o", str(out), "--pose-topic", "/cam/color"]) == 1
    err = capsys.readouterr().err
    assert "'/cam/color' is sensor_msgs/msg/Image: --pose-topic needs" in err
    assert "Traceback" not in err and not out.exists()
    zero = tmp_path / "z_bag"
    write_bag(sun3d / "robot_b", zero, frames=3, zero_stamps=True)
    assert main(["convert", str(zero), "-o", str(out)]) == 1
    assert "two messages on /cam/" in capsys.readouterr().err and not out.exists()
    assert main(["convert", str(bag), "-o", str(out)]) == 0  # the retry is not refused
    for kw, said in (  # no intrinsics to read: named (it said "camera info: False")
        ({"k_zero": 3}, "no CameraInfo on /cam/info with a focal length (K 0?)"),
        ({"info": False}, "the bag has no CameraInfo topic (sensor_msgs/msg/CameraInfo)"),
    ):
        blind = tmp_path / f"k{len(said)}_bag"
        write_bag(sun3d / "robot_b", blind, frames=3, **kw)
        assert main(["convert", str(blind), "-o", str(tmp_path / "blind")]) == 1
        assert said in capsys.readouterr().err and not (tmp_path / "blind").exists()
    late = tmp_path / "late_bag"  # the first CameraInfo uncalibrated, the next ones right
    write_bag(sun3d / "robot_b", late, frames=3, k_zero=1)
    assert main(["convert", str(late), "-o", str(tmp_path / "late")]) == 0
    empty = tmp_path / "e_bag"
    write_bag(sun3d / "robot_b", empty, frames=0)  # its topics, no message on them
    assert main(["convert", str(empty), "-o", str(tmp_path / "e")]) == 1
    err = capsys.readouterr().err
    assert f"{empty}: the image topics ['/cam/color', '/cam/depth'] hold no message" in err


def test_an_error_reading_a_bags_conversion_names_the_bag(sun3d, tmp_path):
    """A bag whose conversion could not be read was named by the cache's folder, which the
    user never made (an outside tester's 5 Hz odometry); the bag now comes first."""
    bag = tmp_path / "mm_bag"
    write_bag(sun3d / "robot_b", bag, frames=3, k_times=0.007)  # a focal length in mm
    with pytest.raises(BadRobotData, match="intrinsics implausible") as exc:
        read_recording(bag)
    assert str(exc.value).startswith(f"{bag} (as converted: ")


def test_a_lone_ros2_storage_file_is_told_its_folder(sun3d, tmp_path):
    """A ROS 2 bag's .db3 given alone: the bag is its folder (metadata.yaml), named."""
    bag = tmp_path / "f_bag"
    write_bag(sun3d / "robot_b", bag, frames=2)
    (db3,) = bag.glob("*.db3")
    assert is_bag(db3)
    with pytest.raises(BadRobotData, match="give the ROS 2 bag's folder") as exc:
        read_recording(db3)
    assert str(exc.value).endswith(f"(with metadata.yaml): {bag}")
