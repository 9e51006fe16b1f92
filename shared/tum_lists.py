"""The TUM RGB-D layout's text lists (`rgb.txt`, `depth.txt`, `groundtruth.txt`): parsing,
and the nearest-timestamp association of their rows (CONTRACT.md section 1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fleetmap.errors import BadRobotData
from fleetmap.geometry import pose_from_tum

#: Timestamps are seconds: a Unix time in seconds is under this until the year 5138, while
#: one in milliseconds (1.7e12 in 2026), microseconds or nanoseconds (ROS: 1.7e18) is over.
MAX_SECONDS = 1e11


def read_list(path: Path) -> list[tuple[float, list[str]]]:
    """Parse a TUM text list: '#' comments and blank lines skipped, sorted by time; a line
    that does not start with a timestamp is BadRobotData naming it."""
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
            raise BadRobotData(
                f"{path}:{n}: expected a timestamp first, got {line.strip()[:60]!r} "
                "(comments start with '#')"
            ) from None
        if not np.isfinite(stamp):
            raise BadRobotData(f"{path}:{n}: non-finite timestamp")
        if abs(stamp) >= MAX_SECONDS:  # would match nothing within 0.02 "s": every frame lost
            raise BadRobotData(
                f"{path}:{n}: timestamp {parts[0]} is not in seconds (a Unix time in seconds "
                "stays under 1e11 until the year 5138): milli-, micro- or nanoseconds? ROS "
                "stamps in nanoseconds divided by 1e9 are seconds"
            )
        rows.append((stamp, parts[1:]))
    rows.sort(key=lambda r: r[0])
    return rows


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


def read_poses(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    rows = read_list(path)
    stamps, poses = [], []
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
    return np.array(stamps), poses
