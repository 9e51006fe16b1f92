"""Robots recorded as ROS bags, read with `rosbags` (pure Python, no ROS install).

A ROS 1 `.bag`, a ROS 2 bag folder (`metadata.yaml`, sqlite3 or MCAP storage) or a lone
`.mcap`/`.db3` file is turned into the TUM layout (CONTRACT.md section 1) in a cache folder,
once per bag and topic choice, and every later stage reads that folder: colour from
`sensor_msgs/Image` (rgb8, bgr8, rgba8, bgra8, mono8) or `sensor_msgs/CompressedImage`
(JPEG or PNG, as image_transport's `compressed` writes it and most bags hold colour), depth
from `sensor_msgs/Image` (16UC1 in millimetres, or 32FC1 in metres, stored as millimetres),
intrinsics from `sensor_msgs/CameraInfo`, camera-to-map poses from
`geometry_msgs/PoseStamped` or `nav_msgs/Odometry` (frame_id = the robot's map frame).
Topics are found by message type
when there is one of each (two images: the one with a depth encoding is depth), else named
with `BagTopics`.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from fleetmap.errors import BadRobotData
from fleetmap.geometry import pose_to_tum

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


@dataclass(frozen=True)
class BagTopics:
    """Topic names to use; None: found by message type."""

    rgb: str | None = None
    depth: str | None = None
    info: str | None = None
    pose: str | None = None


def is_bag(path: Path) -> bool:
    """A ROS 1 bag, a ROS 2 bag folder, or a lone ROS 2 storage file (taken as a bag to be
    told that its folder is the bag: `_reader`)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix in (".bag", ".mcap", ".db3") and path.is_file()


def cached_tum(bag: Path, topics: BagTopics = BagTopics(), cache: Path | None = None) -> Path:
    """The bag as a TUM folder in the cache (made on first use, reused while the bag is
    unchanged)."""
    bag = Path(bag).resolve()
    key = hashlib.sha256(
        json.dumps([str(bag), _bag_state(bag), topics.__dict__]).encode()
    ).hexdigest()[:16]
    root = cache or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "fleetmap"
    out = root / "bags" / f"{bag.stem}-{key}"
    if not (out / "groundtruth.txt").is_file():
        tmp = out.with_name(out.name + f".tmp{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            bag_to_tum(bag, tmp, topics)
        except BaseException:  # no half-converted bag left in the cache
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        shutil.rmtree(out, ignore_errors=True)
        tmp.rename(out)  # whole or not at all
    return out


def read_bag(bag: Path, robot_id, intrinsics, require_depth, require_poses, topics):
    """`dataset.read_recording` of the TUM folder a ROS bag converts to (`cached_tum`), its
    errors naming the bag (they named the cache's folder, which the user never made: an
    outside tester's 5 Hz odometry), the bag as the recording's `source`."""
    from fleetmap.dataset import default_robot_id, read_recording

    tum = cached_tum(bag, topics or BagTopics())
    try:
        rec = read_recording(tum, robot_id or default_robot_id(bag), intrinsics, require_depth,
                             require_poses)  # fmt: skip
    except BadRobotData as exc:
        raise BadRobotData(f"{bag} (as converted: {exc})") from None
    return replace(rec, source=bag)


def _bag_state(bag: Path) -> list:
    """What says a bag changed: a file's size and modification time; a ROS 2 bag folder's,
    each of its files' (rewriting a folder's .db3 and metadata.yaml in place changes
    neither the folder's size nor its time, and the stale conversion was read)."""
    files = sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    return [[str(p.relative_to(bag)), p.stat().st_size, p.stat().st_mtime_ns] for p in files]


def _reader(bag: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = [bag]
    if bag.is_file() and bag.suffix in (".mcap", ".db3"):
        where = f": {bag.parent}" if (bag.parent / "metadata.yaml").is_file() else ""
        raise BadRobotData(f"{bag}: give the ROS 2 bag's folder (with metadata.yaml){where}")
    return AnyReader(paths, default_typestore=get_typestore(Stores.LATEST))


def _pick(conns, types: tuple[str, ...], given: str | None, what: str, flag: str):
    if given is not None:
        found = [c for c in conns if c.topic == given]
        if not found:
            raise BadRobotData(f"no topic {given!r} in the bag ({flag})")
        if found[0].msgtype not in types:  # read as another type: an AttributeError before
            raise BadRobotData(
                f"topic {given!r} is {found[0].msgtype}: {flag} needs {' or '.join(types)}"
            )
        return found[0]
    found = [c for c in conns if c.msgtype in types]
    if not found:  # "0 CameraInfo topics []: choose one": there was none to choose
        raise BadRobotData(f"the bag has no {what} topic ({' or '.join(types)})")
    if len(found) != 1:
        names = sorted(c.topic for c in found)
        raise BadRobotData(f"{len(found)} {what} topics {names}: choose one with {flag}")
    return found[0]


def _images(reader, conns, topics: BagTopics):
    """(rgb connection, depth connection): given, or the two Image topics told apart by
    their first message's encoding."""
    if topics.rgb and topics.depth:
        return (
            _pick(conns, (IMAGE, COMPRESSED), topics.rgb, "colour", "--rgb-topic"),
            _pick(conns, (IMAGE, COMPRESSED), topics.depth, "depth", "--depth-topic"),
        )
    images = [c for c in conns if c.msgtype in (IMAGE, COMPRESSED)]
    if not images:
        raise BadRobotData(
            f"no {IMAGE} or {COMPRESSED} topic in the bag: it holds no colour or depth images"
        )
    rgb, depth = [], []
    for c in images:
        for _, _, msg in _messages(reader, [c]):  # the first message's encoding
            (depth if _is_depth(msg) else rgb).append(c)
            break
    if not rgb and not depth:  # topics declared, nothing recorded on them
        raise BadRobotData(f"the image topics {sorted(c.topic for c in images)} hold no message")
    if topics.rgb:
        rgb = [_pick(conns, (IMAGE, COMPRESSED), topics.rgb, "colour", "--rgb-topic")]
    if topics.depth:
        depth = [_pick(conns, (IMAGE, COMPRESSED), topics.depth, "depth", "--depth-topic")]
    if len(rgb) != 1 or len(depth) != 1:
        raise BadRobotData(
            f"colour image topics {sorted(c.topic for c in rgb)}, depth image topics "
            f"{sorted(c.topic for c in depth)}: choose with --rgb-topic and --depth-topic"
        )
    return rgb[0], depth[0]


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _is_depth(msg) -> bool:
    """Whether an image message holds depth: its encoding, or image_transport's
    compressedDepth format."""
    if hasattr(msg, "encoding"):
        return msg.encoding in DEPTH_ENCODINGS
    return "compressedDepth" in msg.format


def _decoded(msg, depth: bool) -> np.ndarray:
    """A CompressedImage's colour as BGR; compressed depth refused, naming the way out."""
    if depth:
        raise BadRobotData(
            f"compressed depth ({msg.format!r}) is not read: record depth as {IMAGE} "
            "(16UC1 in millimetres or 32FC1 in metres)"
        )
    img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise BadRobotData(f"a compressed colour image ({msg.format!r}) that does not decode")
    return img


def _image(msg, depth: bool) -> np.ndarray:
    if not hasattr(msg, "encoding"):  # a CompressedImage
        return _decoded(msg, depth)
    h, w, enc = msg.height, msg.width, msg.encoding
    data = np.asarray(msg.data, dtype=np.uint8)
    if h < 1 or w < 1 or msg.step < w or data.size < h * msg.step:
        raise BadRobotData(
            f"an image of {w}x{h} pixels, step {msg.step}, holds {data.size} bytes "
            f"(needs {h * msg.step})"
        )
    rows = data[: h * msg.step].reshape(h, msg.step)
    if depth:
        if enc in ("16UC1", "mono16"):
            img = rows[:, : 2 * w].copy().view(">u2" if msg.is_bigendian else "<u2")
            return img.astype(np.uint16)
        if enc == "32FC1":
            m = rows[:, : 4 * w].copy().view(">f4" if msg.is_bigendian else "<f4")
            mm = np.where(np.isfinite(m) & (m > 0), np.round(m * 1000.0), 0)
            return np.clip(mm, 0, 65535).astype(np.uint16)
        raise BadRobotData(f"depth encoding {enc!r}: expected 16UC1 (mm) or 32FC1 (m)")
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
    if enc not in channels:
        raise BadRobotData(f"colour encoding {enc!r}: expected one of {sorted(channels)}")
    img = rows[:, : channels[enc] * w].reshape(h, w, channels[enc])
    convert = {
        "rgb8": cv2.COLOR_RGB2BGR,
        "rgba8": cv2.COLOR_RGBA2BGR,
        "bgra8": cv2.COLOR_BGRA2BGR,
        "mono8": cv2.COLOR_GRAY2BGR,
    }
    return cv2.cvtColor(img, convert[enc]) if enc in convert else img.copy()


def _pose(msg) -> np.ndarray:
    from fleetmap.geometry import pose_from_tum

    p = msg.pose.pose if hasattr(msg, "twist") else msg.pose  # Odometry or PoseStamped
    t = np.array([p.position.x, p.position.y, p.position.z])
    q = np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])
    return pose_from_tum(t, q)


def _camera(msg) -> dict:
    """camera.json's contents from a CameraInfo message (ROS 2 `k`, ROS 1 `K`)."""
    k = msg.k if hasattr(msg, "k") else msg.K
    K = np.asarray(k, dtype=float).reshape(3, 3)
    return {
        "fx": K[0, 0],
        "fy": K[1, 1],
        "cx": K[0, 2],
        "cy": K[1, 2],
        "depth_scale": 1000.0,
        "width": int(msg.width),
        "height": int(msg.height),
    }


def _calibrated(camera: dict) -> dict | None:
    """camera.json's contents where they give a focal length; None for an uncalibrated
    driver's CameraInfo (K all zeros), so that a later message's are taken."""
    return camera if camera["fx"] > 0 and camera["fy"] > 0 else None


def _written(msg, kind: str, stamp: float, out: Path) -> str:
    """A pose ("gt") as its list line, or an image ("rgb", "depth") written to `out` and
    its list line."""
    if kind == "gt":
        return f"{stamp:.9f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(_pose(msg)))
    name = f"{kind}/{stamp:.9f}.png"
    cv2.imwrite(str(out / name), _image(msg, kind == "depth"))
    return f"{stamp:.9f} {name}"


def _messages(reader, connections, bag: Path | None = None):
    """(n, connection, message) of the reader's messages, deserialized; a storage that
    fails mid-read (a cut blob) or a damaged message as BadRobotData (naming `bag` where
    given)."""
    where = "" if bag is None else f"{bag}: "
    it = reader.messages(connections=connections)
    for n in itertools.count():
        try:
            conn, _, raw = next(it)
        except StopIteration:
            return
        except Exception as exc:  # rosbags' own error classes per format
            raise BadRobotData(f"{where}cannot read the bag's messages: {exc}") from exc
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # a damaged message in a readable bag
            raise BadRobotData(f"{where}message {n} on {conn.topic}: {exc}") from exc
        yield n, conn, msg


def _topics_of(reader, bag: Path, topics: BagTopics):
    """The colour, depth, CameraInfo and pose connections; BadRobotData naming the bag."""
    conns = list(reader.connections)
    try:
        rgb_c, depth_c = _images(reader, conns, topics)
        info_c = _pick(conns, (INFO,), topics.info, "CameraInfo", "--info-topic")
        return rgb_c, depth_c, info_c, _pick(conns, POSE_TYPES, topics.pose, "pose", "--pose-topic")
    except BadRobotData as exc:
        raise BadRobotData(f"{bag}: {exc}") from None


def bag_to_tum(bag: Path, out: Path, topics: BagTopics = BagTopics()) -> Path:
    """Write the bag's colour, depth, intrinsics and poses as a TUM folder `out`."""
    bag = Path(bag)
    if not is_bag(bag):
        raise BadRobotData(f"{bag}: not a ROS bag (.bag, or a folder with metadata.yaml)")
    try:
        reader = _reader(bag)
        reader.open()
    except BadRobotData:
        raise
    except Exception as exc:  # rosbags raises its own error classes per format
        why = " ".join(str(exc).split())  # one line (a YAML parser's message spans nine)
        raise BadRobotData(f"{bag}: cannot read the bag: {why}") from exc
    try:
        rgb_c, depth_c, info_c, pose_c = _topics_of(reader, bag, topics)
        for sub in ("rgb", "depth"):
            (out / sub).mkdir(parents=True, exist_ok=True)
        lists = {"rgb": [], "depth": [], "gt": []}
        camera = None
        wanted = [rgb_c, depth_c, info_c, pose_c]
        seen: dict[str, set] = {"rgb": set(), "depth": set(), "gt": set()}
        for n, conn, msg in _messages(reader, wanted, bag):
            if conn.topic == info_c.topic:
                camera = camera or _calibrated(_camera(msg))
                continue
            stamp = _stamp(msg)
            kind = {pose_c.topic: "gt", depth_c.topic: "depth"}.get(conn.topic, "rgb")
            if f"{stamp:.9f}" in seen[kind]:  # one file a stamp: a repeat would pair wrongly
                raise BadRobotData(
                    f"{bag}: two messages on {conn.topic} at header stamp {stamp:.9f}: "
                    "every message needs its own time (stamps all 0?)"
                )
            seen[kind].add(f"{stamp:.9f}")
            try:
                lists[kind].append(_written(msg, kind, stamp, out))
            except (BadRobotData, ValueError, cv2.error) as exc:
                raise BadRobotData(f"{bag}: message {n} on {conn.topic}: {exc}") from exc
    finally:
        reader.close()
    if camera is None or not lists["rgb"] or not lists["depth"] or not lists["gt"]:
        counts = {k: len(v) for k, v in lists.items()}
        why = "" if camera else f", no CameraInfo on {info_c.topic} with a focal length (K 0?)"
        raise BadRobotData(f"{bag}: incomplete recording {counts}{why}")
    (out / "camera.json").write_text(json.dumps(camera, indent=1))
    for name, key in (("rgb.txt", "rgb"), ("depth.txt", "depth"), ("groundtruth.txt", "gt")):
        (out / name).write_text("\n".join(lists[key]) + "\n")
    return out
