"""`fleet.mcap`: the merged fleet for Foxglove (and any MCAP reader), in Foxglove's own
protobuf schemas (`foxglove-schemas-protobuf`), written with the `mcap` library.

Read from what `merge` and `map` already wrote (merged.ply, trajectories/, the report), so
both commands write the same file:

- `/tf`: one `foxglove.FrameTransform` per placed robot but the reference, `REF/map` ->
  `R/map` (T_ref_R);
- `/fleet/R/cloud`: one `foxglove.PointCloud` per placed robot in its own map frame (x y z
  float32, red green blue alpha uint8: the image's colour);
- `/fleet/R/trajectory`: `foxglove.PosesInFrame`, every pose of trajectories/R.txt, in
  the reference's map frame;
- `/fleet/overlaps`: a `foxglove.SceneUpdate` whose entity holds one line per verified
  overlap between two keyframes (LINE_LIST, reference frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fleetmap.geometry import apply, invert, matrix_to_quat

PLY_TYPES = {
    "float": "<f4",
    "uchar": "u1",
    "ushort": "<u2",  # earlier builds' robot index
    "uint16": "<u2",
    "int": "<i4",
    "uint": "<u4",
}
TOPIC_TF, TOPIC_OVERLAPS = "/tf", "/fleet/overlaps"
LINE_COLOUR = (1.0, 0.85, 0.1, 1.0)  # overlaps: yellow over image-coloured clouds


def frame_id(robot: str) -> str:
    """A robot's map frame in the MCAP."""
    return f"{robot}/map"


def read_ply(path: Path) -> np.ndarray:
    """A binary little-endian PLY of vertices (as `fleetmap.mapcloud` writes): a structured
    array with the file's properties as fields."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: expected a binary little-endian PLY, got {header[:2]}")
    n = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    fields = [h.split()[1:] for h in header if h.startswith("property")]
    dtype = np.dtype([(name, PLY_TYPES[kind]) for kind, name in fields])
    return np.frombuffer(data, dtype, count=n, offset=end)


def _read_tum(path: Path) -> np.ndarray:
    """Rows [stamp, tx, ty, tz, qx, qy, qz, qw] of a TUM trajectory file, shape (N, 8)."""
    rows = [ln.split() for ln in path.read_text().splitlines() if ln and ln[0] != "#"]
    return np.array(rows, float).reshape(-1, 8)


def write_fleet_mcap(out: Path, report: dict, lines: list | None = None) -> Path:
    """OUT/fleet.mcap from OUT/merged.ply, OUT/trajectories/ and the report (its robots'
    order indexes merged.ply's `robot` field). The overlap lines: `lines` as the live
    map's `GET /map/lines` gives them ([robot_a, robot_b, xa, ya, za, xb, yb, zb]), else
    the report's overlaps between keyframes of the trajectories. Returns the file's path."""
    from mcap_protobuf.writer import Writer

    ref, transforms = report["reference"] or "fleet", report["transforms"]  # None: none placed
    names = list(report["robots"])
    tracks = {
        r: _read_tum(out / "trajectories" / f"{r}.txt")
        for r in transforms
        if (out / "trajectories" / f"{r}.txt").is_file()
    }
    stamps = [t[:, 0] for t in tracks.values() if len(t)]
    t0 = int(min(s.min() for s in stamps) * 1e9) if stamps else 0
    ply = read_ply(out / "merged.ply") if (out / "merged.ply").is_file() else None
    path = out / "fleet.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        for k, r in enumerate(names):
            if r not in transforms:
                continue
            T_ref_r = np.array(transforms[r], float)
            if r != ref:
                writer.write_message(TOPIC_TF, _frame_transform(ref, r, T_ref_r, t0), t0, t0)
            if ply is not None:
                cloud = _point_cloud(ply[ply["robot"] == k], invert(T_ref_r), r, t0)
                writer.write_message(f"/fleet/{r}/cloud", cloud, t0, t0)
            if r in tracks and len(tracks[r]):
                poses = _poses(tracks[r], ref)
                writer.write_message(f"/fleet/{r}/trajectory", poses, t0, t0)
        if lines is None:
            segments = _overlap_segments(report.get("overlaps", []), tracks)
        else:
            segments = [(ln[2:5], ln[5:8]) for ln in lines]
        scene = _overlap_scene(segments, ref, t0)
        writer.write_message(TOPIC_OVERLAPS, scene, t0, t0)
        writer.finish()
    return path


def _time(ns: int):
    from google.protobuf.timestamp_pb2 import Timestamp

    return Timestamp(seconds=ns // 10**9, nanos=ns % 10**9)


def _pose(T: np.ndarray):
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

    x, y, z, w = matrix_to_quat(T[:3, :3])
    return Pose(
        position=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        orientation=Quaternion(x=x, y=y, z=z, w=w),
    )


def _frame_transform(ref: str, robot: str, T_ref_r: np.ndarray, t_ns: int):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    p = _pose(T_ref_r)
    return FrameTransform(
        timestamp=_time(t_ns),
        parent_frame_id=frame_id(ref),
        child_frame_id=frame_id(robot),
        translation=p.position,
        rotation=p.orientation,
    )


def _point_cloud(rows: np.ndarray, T_r_ref: np.ndarray, robot: str, t_ns: int):
    """The robot's points (PLY rows, reference frame) in its own map frame."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField as F
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    xyz = apply(T_r_ref, np.c_[rows["x"], rows["y"], rows["z"]].astype(float))
    packed = np.zeros(len(rows), [("xyz", "<f4", 3), ("rgba", "u1", 4)])
    packed["xyz"] = xyz
    packed["rgba"] = np.c_[rows["red"], rows["green"], rows["blue"], np.full(len(rows), 255)]
    fields = [F(name=n, offset=4 * i, type=F.FLOAT32) for i, n in enumerate("xyz")]
    fields += [
        F(name=n, offset=12 + i, type=F.UINT8)
        for i, n in enumerate(("red", "green", "blue", "alpha"))
    ]
    return PointCloud(
        timestamp=_time(t_ns),
        frame_id=frame_id(robot),
        pose=_pose(np.eye(4)),
        point_stride=packed.itemsize,
        fields=fields,
        data=packed.tobytes(),
    )


def _poses(rows: np.ndarray, ref: str):
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

    poses = [
        Pose(
            position=Vector3(x=r[1], y=r[2], z=r[3]),
            orientation=Quaternion(x=r[4], y=r[5], z=r[6], w=r[7]),
        )
        for r in rows
    ]
    return PosesInFrame(
        timestamp=_time(int(rows[-1, 0] * 1e9)), frame_id=frame_id(ref), poses=poses
    )


def _overlap_segments(overlaps: list[dict], tracks: dict) -> list[tuple]:
    """The two cameras of each verified overlap whose keyframes are in the trajectories."""
    where = {r: {round(s, 6): p for s, *p in t[:, :4].tolist()} for r, t in tracks.items()}
    segments = []
    for o in overlaps:
        if o.get("source", "cascade") != "cascade":
            continue
        pa = where.get(o["robot_a"], {}).get(round(o["stamp_a"], 6))
        pb = where.get(o["robot_b"], {}).get(round(o["stamp_b"], 6))
        if pa is not None and pb is not None:
            segments.append((pa, pb))
    return segments


def _overlap_scene(segments: list[tuple], ref: str, t_ns: int):
    """One line per verified overlap, between its two keyframes' cameras (reference frame)."""
    from foxglove_schemas_protobuf.Color_pb2 import Color
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
    from foxglove_schemas_protobuf.Point3_pb2 import Point3
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    points = [Point3(x=p[0], y=p[1], z=p[2]) for seg in segments for p in seg]
    line = LinePrimitive(
        type=LinePrimitive.LINE_LIST,
        pose=_pose(np.eye(4)),
        thickness=2.0,
        scale_invariant=True,
        points=points,
        color=Color(r=LINE_COLOUR[0], g=LINE_COLOUR[1], b=LINE_COLOUR[2], a=LINE_COLOUR[3]),
    )
    entity = SceneEntity(
        timestamp=_time(t_ns), frame_id=frame_id(ref), id="verified-overlaps", lines=[line]
    )
    return SceneUpdate(entities=[entity])
