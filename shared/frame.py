"""The frame structure (thesis eq. 2.7) and its versioned binary codec.

A frame is what a robot sends for one keyframe: GIST (global), local features (SIFT
descriptors, their pixel positions and, with depth, their 3D points in the robot's map
frame), the bag of words, and the robot id, timestamp and camera-to-map pose.

Wire format (little-endian), version 1::

    b"FMFS" | u16 version | u16 flags | u32 header_len | header (UTF-8 JSON)
    | gist f16[D] | keypoints f32[N,2] | descriptors u8[N,128]
    | (flags & POINTS) points f32[N,3] | valid bits u8[ceil(N/8)]
    | bow_ids u32[K] | bow_counts u16[K] | u32 CRC-32 of everything before

No pickle anywhere; every size is checked against caps before anything is allocated, and
decoding a valid encoding gives back bit-identical arrays.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from fleetmap.camera import Intrinsics
from fleetmap.errors import BadFrame, BadInput
from fleetmap.geometry import check_transform
from fleetmap.tum_lists import MAX_SECONDS

MAGIC = b"FMFS"
VERSION = 1
FLAG_POSE = 1
FLAG_POINTS = 2
FLAG_INTRINSICS = 4
KNOWN_FLAGS = FLAG_POSE | FLAG_POINTS | FLAG_INTRINSICS

MAX_FEATURES = 4096
MAX_GIST_DIM = 4096
MAX_WORDS = 1 << 20
MAX_HEADER_BYTES = 16 * 1024
MAX_FRAME_BYTES = 4 * 1024 * 1024
ROBOT_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # whole id: fullmatch
_PREFIX = struct.Struct("<4sHHI")


def check_robot_id(robot_id: str) -> str:
    """Robot ids: 1-64 characters of letters, digits, '_', '.', '-' (no leading symbol)."""
    if not isinstance(robot_id, str) or not ROBOT_ID_RE.fullmatch(robot_id):
        raise BadInput(f"Robot id must match {ROBOT_ID_RE.pattern}, got {robot_id!r}")
    return robot_id


@dataclass(eq=False)
class Frame:
    """One keyframe's frame structure.

    Attributes
    ----------
    robot_id : str
    stamp : float, seconds.
    gist : ndarray of shape (D,), float16.
    keypoints : ndarray of shape (N, 2), float32 pixel positions (x, y).
    descriptors : ndarray of shape (N, 128), uint8 SIFT.
    bow_ids, bow_counts : ndarray of shape (K,), uint32 word ids (sorted) and uint16 counts.
    T_map_cam : ndarray of shape (4, 4) float64 camera-to-map pose, or None.
    points : ndarray of shape (N, 3) float32, each feature's point in the map frame
        (metres; zeros where `point_valid` is False), or None without depth.
    point_valid : ndarray of shape (N,) bool, or None.
    width, height : image size in pixels.
    vocab_id : the vocabulary the BoW is over.
    intrinsics : the camera's Intrinsics, or None.
    """

    robot_id: str
    stamp: float
    gist: np.ndarray
    keypoints: np.ndarray
    descriptors: np.ndarray
    bow_ids: np.ndarray
    bow_counts: np.ndarray
    T_map_cam: np.ndarray | None = None
    points: np.ndarray | None = None
    point_valid: np.ndarray | None = None
    width: int = 640
    height: int = 480
    vocab_id: str = ""
    intrinsics: Intrinsics | None = None

    def __post_init__(self) -> None:
        validate(self)

    @property
    def n_features(self) -> int:
        return len(self.keypoints)


def _arr(value, dtype, shape: tuple, name: str) -> np.ndarray:
    """Check dtype and shape (-1 = any length) without silent casts of other kinds."""
    a = np.asarray(value)
    if a.dtype != dtype:
        if a.dtype.kind != np.dtype(dtype).kind or a.dtype.itemsize > np.dtype(dtype).itemsize:
            raise BadInput(f"Expected {name} of dtype {np.dtype(dtype)}, got {a.dtype}")
        a = a.astype(dtype)
    if a.ndim != len(shape) or any(s not in (-1, d) for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ")"
        raise BadInput(f"Expected {name} of shape {want}, got {a.shape}")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise BadInput(f"{name} has non-finite values (NaN or inf)")
    return np.ascontiguousarray(a)


def validate(f: Frame) -> None:
    """Check every field's type, shape, dtype, range and finiteness; BadInput otherwise."""
    check_robot_id(f.robot_id)
    if (
        isinstance(f.stamp, bool)
        or not isinstance(f.stamp, int | float)
        or not np.isfinite(f.stamp)
    ):
        raise BadInput(f"stamp must be a finite number, got {f.stamp!r}")
    if not 0 <= f.stamp < MAX_SECONDS:  # a robot's clock: seconds, never before its start
        raise BadInput(
            f"stamp must be seconds in [0, {MAX_SECONDS:g}), got {f.stamp!r}"
            + " (nanoseconds? send seconds)" * (f.stamp >= MAX_SECONDS)
        )
    f.stamp = float(f.stamp)
    f.gist = _arr(f.gist, np.float16, (-1,), "gist")
    if not 0 < len(f.gist) <= MAX_GIST_DIM:
        raise BadInput(f"gist must have 1..{MAX_GIST_DIM} values, got {len(f.gist)}")
    f.keypoints = _arr(f.keypoints, np.float32, (-1, 2), "keypoints")
    n = len(f.keypoints)
    if n > MAX_FEATURES:
        raise BadInput(f"At most {MAX_FEATURES} features per frame, got {n}")
    f.descriptors = _arr(f.descriptors, np.uint8, (n, 128), "descriptors")
    f.bow_ids = _arr(f.bow_ids, np.uint32, (-1,), "bow_ids")
    f.bow_counts = _arr(f.bow_counts, np.uint16, (len(f.bow_ids),), "bow_counts")
    if len(f.bow_ids) > MAX_FEATURES or np.any(np.diff(f.bow_ids.astype(np.int64)) <= 0):
        raise BadInput("bow_ids must be strictly increasing, at most one per feature")
    if f.T_map_cam is not None:
        f.T_map_cam = check_transform(f.T_map_cam, "T_map_cam")
    if (f.points is None) != (f.point_valid is None):
        raise BadInput("points and point_valid come together")
    if f.points is not None:
        f.points = _arr(f.points, np.float32, (n, 3), "points")
        f.point_valid = _arr(f.point_valid, np.bool_, (n,), "point_valid")
    if not (
        isinstance(f.width, int)
        and isinstance(f.height, int)
        and 0 < f.width <= 16384
        and 0 < f.height <= 16384
    ):
        raise BadInput(f"Image size out of range: {f.width}x{f.height}")
    if n and (
        np.any(f.keypoints < -1)
        or np.any(f.keypoints[:, 0] > f.width + 1)
        or np.any(f.keypoints[:, 1] > f.height + 1)
    ):
        raise BadInput(f"keypoints outside the {f.width}x{f.height} image")
    if not isinstance(f.vocab_id, str) or len(f.vocab_id) > 64:
        raise BadInput("vocab_id must be a string of at most 64 characters")


def encode(f: Frame) -> bytes:
    """Serialise a validated frame to the version-1 wire format."""
    validate(f)
    flags = (
        FLAG_POSE * (f.T_map_cam is not None)
        | FLAG_POINTS * (f.points is not None)
        | FLAG_INTRINSICS * (f.intrinsics is not None)
    )
    header = {
        "robot_id": f.robot_id,
        "stamp": f.stamp,
        "width": f.width,
        "height": f.height,
        "vocab_id": f.vocab_id,
        "n_features": f.n_features,
        "gist_dim": len(f.gist),
        "n_words": len(f.bow_ids),
        "T_map_cam": f.T_map_cam.reshape(-1).tolist() if f.T_map_cam is not None else None,
        "intrinsics": f.intrinsics.to_dict() if f.intrinsics is not None else None,
    }
    hb = json.dumps(header, allow_nan=False, separators=(",", ":")).encode()
    parts = [
        _PREFIX.pack(MAGIC, VERSION, flags, len(hb)),
        hb,
        f.gist.astype("<f2").tobytes(),
        f.keypoints.astype("<f4").tobytes(),
        f.descriptors.tobytes(),
    ]
    if f.points is not None:
        parts += [f.points.astype("<f4").tobytes(), np.packbits(f.point_valid).tobytes()]
    parts += [f.bow_ids.astype("<u4").tobytes(), f.bow_counts.astype("<u2").tobytes()]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


class _Reader:
    def __init__(self, buf: bytes, start: int):
        self.buf, self.pos = buf, start

    def take(self, dtype: str, count: int, name: str) -> np.ndarray:
        nbytes = np.dtype(dtype).itemsize * count
        if self.pos + nbytes > len(self.buf) - 4:
            raise BadFrame(
                f"Truncated frame: {name} needs {nbytes} bytes at offset {self.pos}, "
                f"only {len(self.buf) - 4 - self.pos} left"
            )
        a = np.frombuffer(self.buf, dtype=dtype, count=count, offset=self.pos)
        self.pos += nbytes
        return a.astype(np.dtype(dtype).newbyteorder("="))


def _unique_keys(pairs: list) -> dict:
    """A JSON object whose keys are each given once (two "stamp"s: which one was meant?)."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen = [k for k, _ in pairs]
        raise ValueError(f"key {next(k for k in seen if seen.count(k) > 1)!r} given twice")
    return out


def _header(buf: bytes) -> tuple[int, dict, int]:
    if len(buf) > MAX_FRAME_BYTES:
        raise BadFrame(f"Frame of {len(buf)} bytes exceeds the {MAX_FRAME_BYTES}-byte limit")
    if len(buf) < _PREFIX.size + 4:
        raise BadFrame(f"Truncated frame: {len(buf)} bytes")
    magic, version, flags, hlen = _PREFIX.unpack_from(buf)
    if magic != MAGIC:
        raise BadFrame(f"Not a fleetmap frame (magic {magic!r}, expected {MAGIC!r})")
    if version != VERSION:
        raise BadFrame(f"Frame format version {version}, this build reads {VERSION}")
    if flags & ~KNOWN_FLAGS:
        raise BadFrame(f"Unknown frame flag bits {flags & ~KNOWN_FLAGS:#x}")
    if hlen > MAX_HEADER_BYTES or _PREFIX.size + hlen > len(buf) - 4:
        raise BadFrame(f"Header of {hlen} bytes is truncated or over the limit")
    (crc,) = struct.unpack_from("<I", buf, len(buf) - 4)
    if zlib.crc32(memoryview(buf)[:-4]) != crc:
        raise BadFrame("Frame checksum mismatch (corrupted or truncated)")
    try:
        header = json.loads(
            buf[_PREFIX.size : _PREFIX.size + hlen].decode(),
            parse_constant=_reject_constant,
            object_pairs_hook=_unique_keys,
        )
        if not isinstance(header, dict):
            raise ValueError("header is not an object")
    except RecursionError as exc:
        raise BadFrame("Bad frame header: JSON nested too deep") from exc
    except (UnicodeDecodeError, ValueError) as exc:
        raise BadFrame(f"Bad frame header: {exc}") from exc
    return flags, header, _PREFIX.size + hlen


def _reject_constant(name: str):
    raise ValueError(f"non-finite number {name} in header")


def _count(header: dict, key: str, cap: int) -> int:
    v = header.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= cap:
        raise BadFrame(f"Header field {key!r} must be an integer in 0..{cap}, got {v!r}")
    return v


def decode(buf: bytes) -> Frame:
    """Parse and validate an encoded frame; BadFrame with the reason on any defect."""
    buf = bytes(buf)
    flags, h, start = _header(buf)
    n = _count(h, "n_features", MAX_FEATURES)
    d = _count(h, "gist_dim", MAX_GIST_DIM)
    k = _count(h, "n_words", MAX_FEATURES)
    r = _Reader(buf, start)
    gist = r.take("<f2", d, "gist")
    kp = r.take("<f4", 2 * n, "keypoints").reshape(n, 2)
    desc = r.take("u1", 128 * n, "descriptors").reshape(n, 128)
    points = valid = None
    if flags & FLAG_POINTS:
        points = r.take("<f4", 3 * n, "points").reshape(n, 3)
        valid = np.unpackbits(r.take("u1", (n + 7) // 8, "point_valid"), count=n).astype(bool)
    ids = r.take("<u4", k, "bow_ids")
    counts = r.take("<u2", k, "bow_counts")
    if r.pos != len(buf) - 4:
        raise BadFrame(f"{len(buf) - 4 - r.pos} unexpected trailing bytes")
    try:
        T = h.get("T_map_cam") if flags & FLAG_POSE else None
        intr = Intrinsics.from_dict(h["intrinsics"]) if flags & FLAG_INTRINSICS else None
        return Frame(
            robot_id=h.get("robot_id"),
            stamp=h.get("stamp"),
            gist=gist,
            keypoints=kp,
            descriptors=desc,
            bow_ids=ids,
            bow_counts=counts,
            T_map_cam=None if T is None else np.array(T, dtype=np.float64).reshape(4, 4),
            points=points,
            point_valid=valid,
            width=h.get("width"),
            height=h.get("height"),
            vocab_id=h.get("vocab_id", ""),
            intrinsics=intr,
        )
    except (BadInput, TypeError, ValueError, KeyError, OverflowError) as exc:
        raise BadFrame(f"Invalid frame: {exc}") from exc
