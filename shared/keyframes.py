"""Keyframe selection: a new keyframe when the robot has moved or turned enough since the
last one, or when a time interval has passed.

The thesis adds one image per second at 3 km/h (about 0.8 m apart). RGB-D map merging wants
denser views of the overlap (every pooled pair of views adds spread, thesis Table 3.5), so
the defaults take one every 5 cm or 5 degrees, and at least one per second.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmap.geometry import invert, rotation_angle_deg


@dataclass(frozen=True)
class KeyframePolicy:
    """Thresholds: metres, degrees and seconds since the last keyframe."""

    min_translation_m: float = 0.05
    min_rotation_deg: float = 5.0
    max_interval_s: float | None = 1.0
    min_interval_s: float = 0.0


DEFAULT_POLICY = KeyframePolicy()


def select_keyframes(
    stamps: Sequence[float],
    poses: Sequence[np.ndarray | None],
    policy: KeyframePolicy | None = None,
) -> list[int]:
    """Indices of the keyframes among frames in time order.

    Parameters
    ----------
    stamps : sequence of N timestamps (s), increasing.
    poses : sequence of N camera-to-map 4x4 poses, or None where unknown (then only the
        time interval applies).

    Returns
    -------
    list of int, always starting with 0 when N > 0.
    """
    policy = policy or DEFAULT_POLICY
    if len(stamps) == 0:
        return []
    keep = [0]
    for i in range(1, len(stamps)):
        last = keep[-1]
        dt = stamps[i] - stamps[last]
        if dt < policy.min_interval_s:
            continue
        if policy.max_interval_s is not None and dt >= policy.max_interval_s:
            keep.append(i)
            continue
        if poses[i] is None or poses[last] is None:
            continue
        rel = invert(poses[last]) @ poses[i]
        if (
            np.linalg.norm(rel[:3, 3]) >= policy.min_translation_m
            or rotation_angle_deg(rel[:3, :3]) >= policy.min_rotation_deg
        ):
            keep.append(i)
    return keep
