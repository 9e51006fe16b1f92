import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.errors import BadFrame, BadInput
from fleetmap.extract import FrameExtractor
from fleetmap.frame import MAX_FEATURES, MAX_FRAME_BYTES, Frame, check_robot_id, decode, encode
from tests.helpers import make_frame


@pytest.fixture(scope="module")
def real_frame(sun3d, vocabulary) -> Frame:
    rec = read_recording(sun3d / "robot_b")
    r = rec.frames[10]
    return FrameExtractor(vocabulary)(
        rec.robot_id,
        r.stamp,
        load_rgb(r.rgb_path),
        load_depth(r.depth_path),
        rec.intrinsics,
        r.T_map_cam,
    )


def _fields(f: Frame) -> dict:
    return {k: getattr(f, k) for k in f.__dataclass_fields__}


def test_real_frame_round_trips_bit_exactly(real_frame):
    buf = encode(real_frame)
    g = decode(buf)
    for k, v in _fields(real_frame).items():
        w = getattr(g, k)
        if isinstance(v, np.ndarray):
            assert v.dtype == w.dtype and v.shape == w.shape, k
            assert v.tobytes() == w.tobytes(), k
        else:
            assert v == w, k
    assert encode(g) == buf


def test_real_frame_has_map_points_and_is_compact(real_frame):
    n = real_frame.n_features
    assert real_frame.point_valid.mean() > 0.5
    # thesis: 1,536 B GIST + 512 B per float32 SIFT; we must stay under a third of it
    assert len(encode(real_frame)) <= (1536 + 512 * n) / 3


def test_truncated_and_corrupted_frames_are_rejected(real_frame):
    buf = encode(real_frame)
    for cut in (0, 5, 20, len(buf) // 2, len(buf) - 1):
        with pytest.raises(BadFrame, match="Truncated|checksum|truncated"):
            decode(buf[:cut])
    flipped = bytearray(buf)
    flipped[len(buf) // 2] ^= 0xFF
    with pytest.raises(BadFrame, match="checksum"):
        decode(bytes(flipped))
    with pytest.raises(BadFrame, match="magic"):
        decode(b"JUNK" + buf[4:])


def test_oversized_frame_is_rejected_before_parsing():
    with pytest.raises(BadFrame, match="exceeds"):
        decode(b"FMFS" + bytes(MAX_FRAME_BYTES))


def test_header_lies_are_caught(real_frame):
    """A frame whose header claims more features than the body holds, with a valid CRC."""
    buf = encode(real_frame)
    hlen = struct.unpack_from("<I", buf, 8)[0]
    header = buf[12 : 12 + hlen].replace(
        f'"n_features":{real_frame.n_features}'.encode(), b'"n_features":4000'
    )
    body = buf[:8] + struct.pack("<I", len(header)) + header + buf[12 + hlen : -4]
    with pytest.raises(BadFrame, match="Truncated frame: keypoints|descriptors"):
        decode(body + struct.pack("<I", zlib.crc32(body)))


@pytest.mark.parametrize(
    "kw, msg",
    [
        (
            {"points": np.full((5, 3), np.nan, np.float32), "point_valid": np.ones(5, bool)},
            "non-finite",
        ),
        ({"gist": np.full(384, np.inf, np.float16)}, "non-finite"),
        ({"descriptors": np.zeros((4, 128), np.uint8)}, r"descriptors of shape \(5, 128\)"),
        ({"keypoints": np.zeros((5, 3), np.float32)}, r"keypoints of shape \(N, 2\)"),
        ({"descriptors": np.zeros((5, 128), np.float32)}, "dtype uint8"),
        ({"robot_id": "../etc"}, "Robot id"),
        ({"stamp": float("nan")}, "stamp"),
        ({"T_map_cam": np.eye(3)}, r"shape \(4, 4\)"),
        ({"T_map_cam": np.zeros((4, 4))}, "bottom row"),
        ({"T_map_cam": np.diag([2.0, 2.0, 2.0, 1.0])}, "must be rigid"),
        ({"T_map_cam": np.diag([1.0, 1.0, -1.0, 1.0])}, "must be rigid"),
        (
            {"T_map_cam": np.array([[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])},
            "translation exceeds",
        ),
        ({"stamp": True}, "stamp"),
        # stored with 201 before, and listed in /robots and /overlaps (an outside tester)
        ({"stamp": -5.0}, r"stamp must be seconds in \[0, 1e\+11\)"),
        ({"stamp": 1e18}, "nanoseconds"),
        ({"stamp": 1e300}, "nanoseconds"),
        ({"bow_ids": np.array([2, 1], np.uint32)}, "strictly increasing"),
        ({"keypoints": np.full((5, 2), 5000, np.float32)}, "outside"),
        (
            {
                "keypoints": np.zeros((MAX_FEATURES + 1, 2), np.float32),
                "descriptors": np.zeros((MAX_FEATURES + 1, 128), np.uint8),
            },
            "At most",
        ),
    ],
)
def test_validation_names_the_problem(kw, msg):
    with pytest.raises(BadInput, match=msg):
        make_frame(**kw)


def test_minimal_frame_without_depth_round_trips():
    f = make_frame()
    g = decode(encode(f))
    assert g.points is None and g.T_map_cam is None
    assert g.gist.tobytes() == f.gist.tobytes()


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=4096))
def test_random_bytes_raise_only_clean_errors(data):
    with pytest.raises(BadFrame):
        decode(data)


@settings(max_examples=300, deadline=None)
@given(st.integers(min_value=0), st.integers(min_value=0, max_value=255))
def test_mutated_frames_raise_only_clean_errors_or_decode(pos, byte):
    buf = bytearray(encode(make_frame()))
    buf[pos % len(buf)] = byte
    try:
        decode(bytes(buf))
    except BadFrame:
        pass


def _reframed(buf: bytes, header: bytes | None = None, flags: int | None = None) -> bytes:
    """`buf` with its header and/or flags replaced and a valid CRC: what a client could send."""
    magic, version, old_flags, hlen = struct.unpack_from("<4sHHI", buf)
    header = buf[12 : 12 + hlen] if header is None else header
    prefix = struct.pack(
        "<4sHHI", magic, version, old_flags if flags is None else flags, len(header)
    )
    body = prefix + header + buf[12 + hlen : -4]
    return body + struct.pack("<I", zlib.crc32(body))


def test_hostile_headers_are_clean_errors():
    """Issue 15: a header nested 5,000 deep was a 500 (RecursionError); unknown flag bits
    were accepted."""
    buf = encode(make_frame())
    with pytest.raises(BadFrame, match="nested too deep"):
        decode(_reframed(buf, header=b"[" * 5000 + b"]" * 5000))
    with pytest.raises(BadFrame, match="Unknown frame flag bits 0x80"):
        decode(_reframed(buf, flags=0x80))
    digits = b'{"robot_id": "r1", "stamp": ' + b"9" * 5000 + b"}"
    with pytest.raises(BadFrame, match="Bad frame header|Invalid frame"):
        decode(_reframed(buf, header=digits))


def test_a_header_key_given_twice_is_refused():
    """Two "stamp" keys: the last one was taken, unsaid (an outside tester's review)."""
    buf = encode(make_frame())
    hlen = struct.unpack_from("<I", buf, 8)[0]
    header = buf[12 : 12 + hlen]
    twice = header[:-1] + b',"stamp":5.0}'
    with pytest.raises(BadFrame, match="'stamp' given twice"):
        decode(_reframed(buf, header=twice))


@pytest.mark.parametrize("bad", ["sa\n", "sa\r\n", "\nsa", "sa\x00", "-sa", "a" * 65, ""])
def test_robot_ids_are_matched_whole(bad):
    """Issue 26.9: `$` let "sa\\n" through as a second robot beside "sa"."""
    assert check_robot_id("sa") == "sa"
    with pytest.raises(BadInput, match="Robot id must match"):
        check_robot_id(bad)
