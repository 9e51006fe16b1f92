"""Choosing the RGB-D pairs to align from two robots' verified overlaps."""

from __future__ import annotations

import numpy as np

from shared.correspondences import RGBDView
from shared.dataset import FrameRecord, Recording, load_depth, load_rgb
from shared.errors import BadRobotData


def frame_at(rec: Recording, stamp: float, tol: float = 1e-3) -> int:
    """Index of the recording's frame at `stamp`."""
    stamps = np.array([f.stamp for f in rec.frames])
    i = int(np.argmin(np.abs(stamps - stamp)))
    if abs(stamps[i] - stamp) > tol:
        raise BadRobotData(f"{rec.robot_id}: no frame at stamp {stamp} (nearest {stamps[i]})")
    return i


def select_pairs(
    overlaps: list[dict],
    rec_a: Recording,
    rec_b: Recording,
    max_pairs: int = 24,
    expand: int = 2,
    step: int = 5,
) -> list[tuple[int, int]]:
    """Frame index pairs (a, b) to align: the verified overlaps, each widened to the grid of
    frames up to `expand` x `step` frames before and after on both robots (neighbours of a
    verified pair usually overlap too, and the place database verifies few pairs across
    wide baselines), then a spread-out subset.

    Spread: greedy farthest-point selection on both cameras' positions, starting from
    the pair with most inliers (thesis Table 3.5: spread matters more than count).
    """
    if not overlaps:
        return []
    seeds = sorted(overlaps, key=lambda o: -o["inliers"])
    cand: list[tuple[int, int]] = []
    for o in seeds:
        i, j = frame_at(rec_a, o["stamp_a"]), frame_at(rec_b, o["stamp_b"])
        for da in range(-expand, expand + 1):
            for db in range(-expand, expand + 1):
                ii, jj = i + da * step, j + db * step
                if 0 <= ii < len(rec_a) and 0 <= jj < len(rec_b) and (ii, jj) not in cand:
                    cand.append((ii, jj))
    # spread over both robots' camera positions (each in its own map frame)
    pos = np.array(
        [np.concatenate([_position(rec_a.frames[i]), _position(rec_b.frames[j])]) for i, j in cand]
    )
    chosen = [0]
    dist = np.linalg.norm(pos - pos[0], axis=1)
    while len(chosen) < min(max_pairs, len(cand)):
        k = int(np.argmax(dist))
        if dist[k] <= 0 and len(chosen) >= len(seeds):
            break
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(pos - pos[k], axis=1))
    return [cand[k] for k in chosen]


def _position(f: FrameRecord) -> np.ndarray:
    return np.zeros(3) if f.T_map_cam is None else f.T_map_cam[:3, 3]


def load_view(rec: Recording, i: int) -> RGBDView:
    f = rec.frames[i]
    if f.depth_path is None or f.T_map_cam is None:
        raise BadRobotData(f"{rec.robot_id}: frame {f.stamp} has no depth or pose")
    return RGBDView(
        load_rgb(f.rgb_path), load_depth(f.depth_path), rec.intrinsics, f.T_map_cam, f.stamp
    )
