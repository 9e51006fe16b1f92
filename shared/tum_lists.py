"""The TUM RGB-D layout's text lists (`rgb.txt`, `depth.txt`, `groundtruth.txt`): parsing,
and the nearest-timestamp association of their rows (CONTRACT.md section 1)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fleetmap.errors import BadRobotData
from fleetmap.geometry import interpolate_pose, pose_from_tum

log = logging.getLogger(__name__)

#: Timestamps are seconds: a Unix time in seconds is under this until the year 5138, while
#: one in milliseconds (1.7e12 in 2026), microseconds or nanoseconds (ROS: 1.7e18) is over.
MAX_SECONDS = 1e11
#: A list whose times reach MAX_SECONDS is in the first of these units its largest reaches:
#: (unit, seconds per unit, from). Kept as written, its rows matched nothing within 0.02
#: "s" in the other lists, or only their exact copies.
UNITS = (("nanoseconds", 1e-9, 1e17), ("microseconds", 1e-6, 1e14), ("milliseconds", 1e-3, 0))


def read_list(path: Path, near: float | None = None) -> list[tuple[float, list[str]]]:
    """Parse a TUM text list: '#' comments and blank lines skipped, sorted by time, in
    seconds (`in_seconds`; `near`: the colour list's median time in seconds); a line that
    does not start with a timestamp is BadRobotData naming it."""
    if not path.is_file():
        raise BadRobotData(f"Missing file: {path}")
    rows = []
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            stamp = float(parts[0])
        except ValueError:  # skipped silently before: a damaged list lost frames unsaid
            hint = "fields apart by spaces, not commas" if "," in parts[0] else "comments: '#'"
            raise BadRobotData(
                f"{path}:{n}: expected a timestamp first, got {line.strip()[:60]!r} ({hint})"
            ) from None
        if not np.isfinite(stamp):
            raise BadRobotData(f"{path}:{n}: non-finite timestamp")
        rows.append((stamp, parts[1:]))
    rows.sort(key=lambda r: r[0])
    return in_seconds(path, rows, near)


def in_seconds(path: Path, rows: list, near: float | None = None) -> list:
    """`rows` with their times in seconds: those of a list whose times reach MAX_SECONDS
    (ROS writes nanoseconds) divided into seconds, as `UNITS` reads them, and said; with
    `near` (the colour list's median time, seconds), in the unit that brings the list's
    median nearest it (an outside tester's poses in nanoseconds since boot, 6.2e12, beside
    images in seconds since boot, 6239: read as milliseconds, no frame had a pose)."""
    big = max((abs(t) for t, _ in rows), default=0.0)
    if big < MAX_SECONDS:
        return rows
    unit, factor = next((u, f) for u, f, lo in UNITS if big >= lo)
    if near is not None:
        mid = float(np.median([t for t, _ in rows]))
        unit, factor = min(((u, f) for u, f, _ in UNITS), key=lambda uf: abs(mid * uf[1] - near))
    log.warning(
        "%s: times up to %.4g read as %s (a Unix time in seconds stays under %g until the "
        "year 5138)", path, big, unit, MAX_SECONDS,
    )  # fmt: skip
    return [(t * factor, v) for t, v in rows]


def associate(a: np.ndarray, b: np.ndarray, max_gap: float) -> list[tuple[int, int]]:
    """Greedy one-to-one nearest-timestamp association, as TUM's associate.py.

    a, b: ndarray of shape (N,) and (M,), sorted stamps. Returns index pairs (i, j).
    """
    if len(a) == 0 or len(b) == 0:
        return []
    j = np.clip(np.searchsorted(b, a), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(a), int)
    cand = []
    for i in range(len(a)):
        for jj in {int(j[i]) - 1, int(j[i])} if len(b) > 1 else {0}:
            gap = abs(a[i] - b[jj])
            if gap <= max_gap:
                cand.append((gap, i, jj))
    cand.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, jj in cand:
        if i not in used_a and jj not in used_b:
            used_a.add(i)
            used_b.add(jj)
            pairs.append((i, jj))
    return sorted(pairs)


#: A colour frame with no pose within the association's gap takes one interpolated between
#: the poses before and after it where those are at most this far apart (seconds): a SLAM's
#: or odometry's 10 Hz track with its jitter, whose rows fall between a 30 Hz camera's
#: images (an outside tester's poses 33 ms off every image: no frame associated, the robot
#: refused). Linear in position, spherical in rotation, off by about a dt^2 / 8 at an
#: acceleration a (5.6 mm at 2 m/s^2); a longer gap is a break in tracking, not bridged.
MAX_POSE_INTERVAL_S = 0.15
#: A Unix time in seconds as a double resolves 0.2 microseconds: poses 0.15 s apart read as
#: 0.1500001 and 0.1499999 (an outside tester's 6.67 Hz track: 23 of 40 frames kept)
STAMP_SLACK_S = 1e-4


def poses_at(t: np.ndarray, pose_t: np.ndarray, poses: list, max_gap: float) -> dict:
    """The pose (4x4) of each of the sorted stamps `t` that has one, by index into `t`: the
    nearest within `max_gap` (`associate`, one to one, as TUM's tools), else interpolated
    between the two around it where they are at most MAX_POSE_INTERVAL_S apart."""
    out = {i: poses[j] for i, j in associate(t, pose_t, max_gap)}
    keys, first = np.unique(pose_t, return_index=True)  # a stamp listed twice: its first
    if len(keys) < 2:
        return out
    k = np.searchsorted(keys, t)
    inside = (k > 0) & (k < len(keys))
    k = np.clip(k, 1, len(keys) - 1)
    near = inside & (keys[k] - keys[k - 1] <= MAX_POSE_INTERVAL_S + STAMP_SLACK_S)
    todo = [i for i in np.flatnonzero(near) if i not in out]
    if not todo:
        return out
    for i in todo:
        lo, hi = keys[k[i] - 1], keys[k[i]]
        T0, T1 = poses[first[k[i] - 1]], poses[first[k[i]]]
        out[i] = interpolate_pose(T0, T1, (t[i] - lo) / (hi - lo))
    log.info("%d frames' poses interpolated between poses up to %g s apart", len(todo),
             MAX_POSE_INTERVAL_S)  # fmt: skip
    return out


#: A pose's quaternion further than this from unit length is said: no rounding of a written
#: one (TUM writes four decimals) comes near it, while columns shifted by one (an index
#: before tx, the quaternion's w first) mostly do.
QUATERNION_SLACK = 0.05


def read_poses(path: Path, near: float | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """`groundtruth.txt`'s times and camera-to-map poses ("timestamp tx ty tz qx qy qz qw");
    `near` as `read_list`'s."""
    rows = read_list(path, near)
    stamps, poses, norms = [], [], []
    for stamp, vals in rows:
        if len(vals) < 7:
            raise BadRobotData(f"{path}: expected 'timestamp tx ty tz qx qy qz qw', got {vals}")
        try:
            v = np.array(vals[:7], dtype=np.float64)
            if not np.isfinite(v).all():
                raise ValueError(f"non-finite values {vals[:7]}")
            poses.append(pose_from_tum(v[:3], v[3:7]))
        except ValueError as exc:
            raise BadRobotData(f"{path}: bad pose at t={stamp}: {exc}") from exc
        stamps.append(stamp)
        norms.append(np.linalg.norm(v[3:7]))
    _said_twice(path, stamps, poses)
    norms = np.array(norms)
    off = norms[np.abs(norms - 1) > QUATERNION_SLACK]
    if len(off):  # normalised as before (the same rotation), but said
        log.warning(
            "%s: %d of %d quaternions %.3g-%.3g long, not 1 (normalised): are the columns "
            "'timestamp tx ty tz qx qy qz qw'?", path, len(off), len(norms), off.min(), off.max(),
        )  # fmt: skip
    return np.array(stamps), poses


def _said_twice(path: Path, stamps: list, poses: list) -> None:
    """Stamps listed twice with different poses said (the first is taken: an outside
    tester's bogus first copies moved a robot 1.7 m unsaid)."""
    seen, twice = {}, 0
    for t, T in zip(stamps, poses, strict=True):
        if t in seen and not np.allclose(seen[t], T, atol=1e-6):
            twice += 1
        seen.setdefault(t, T)
    if twice:
        log.warning("%s: %d times listed twice with different poses: the first of each taken",
                    path, twice)  # fmt: skip
