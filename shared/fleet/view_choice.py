"""Choosing the RGB-D views to align from two robots' verified overlaps (`fleetmap merge`,
`fleetmap align` and the live merge worker choose alike)."""

from __future__ import annotations

import logging

import numpy as np

from fleetmap.correspondences import RGBDView
from fleetmap.dataset import FrameRecord, Recording
from fleetmap.errors import BadRobotData, NoDepthReading
from fleetmap.fleet.types import DEFAULT_VIEWS, Fit

log = logging.getLogger(__name__)


def overlaps_to_align(db, robot_a: str, robot_b: str, wait: float = 0.0) -> list[dict]:
    """The overlaps between two robots (a `PlaceDBClient`'s items) to choose views from:
    the verified and co-visible ones, or where there is none, the place database's
    nominated keyframe pairs (`fleetmap.place.nominate`): the aligner's gate decides."""
    pairs = db.overlaps(robot_a, robot_b, wait=wait)
    return pairs or db.overlaps(robot_a, robot_b, source="nominated")


def frame_at(rec: Recording, stamp: float, tol: float = 1e-3) -> int:
    """Index of the recording's frame at `stamp`."""
    stamps = np.array([f.stamp for f in rec.frames])
    i = int(np.argmin(np.abs(stamps - stamp)))
    if abs(stamps[i] - stamp) > tol:
        raise BadRobotData(f"{rec.robot_id}: no frame at stamp {stamp} (nearest {stamps[i]})")
    return i


def select_views(
    overlaps: list[dict],
    rec_a: Recording,
    rec_b: Recording,
    keyframes_a: list[int] | None = None,
    keyframes_b: list[int] | None = None,
    max_views: int = DEFAULT_VIEWS.max_views,
    radius_m: float = DEFAULT_VIEWS.radius_m,
) -> tuple[list[int], list[int]]:
    """Frame indices of each robot's views to align, from the verified overlaps: the
    verified keyframes, then keyframes looking at the same part of the robot's map (look-at
    points, 1.5 m along the optical axis, within `radius_m` of a verified one's), spread out
    by farthest-point sampling, at most `max_views` per robot.

    Every A view is then paired with every B view: across wide baselines the place database
    verifies few pairs (SUN3D: 1 of 130 co-visible), and the aligner's per-pair hypotheses
    need the pairs it did not verify."""
    if not overlaps:
        return [], []
    seeds = sorted(overlaps, key=lambda o: -o["inliers"])
    out = []
    for rec, key, kfs in ((rec_a, "stamp_a", keyframes_a), (rec_b, "stamp_b", keyframes_b)):
        seed = list(dict.fromkeys(frame_at(rec, o[key]) for o in seeds))
        cand = list(dict.fromkeys(seed + list(kfs if kfs is not None else range(len(rec)))))
        look = np.array([look_at(rec.frames[i].T_map_cam) for i in cand])
        out.append(sorted(cand[k] for k in spread(len(seed), look, max_views, radius_m)))
    return out[0], out[1]


def spread(
    n_seeds: int, look: np.ndarray, max_views: int, radius_m: float = DEFAULT_VIEWS.radius_m
) -> list[int]:
    """Indices of the views to align among candidates whose first `n_seeds` are the verified
    keyframes (best first): the seeds, then candidates whose look-at points (`look`, (N, 3))
    lie within `radius_m` of a seed's, by farthest-point sampling, `max_views` in all."""
    d_seed = np.min(np.linalg.norm(look[:, None] - look[None, :n_seeds], axis=2), axis=1)
    near = [k for k in range(len(look)) if d_seed[k] <= radius_m]
    chosen = list(range(min(n_seeds, max_views)))
    dist = np.min(np.linalg.norm(look[near][:, None] - look[chosen][None], axis=2), axis=1)
    while len(chosen) < min(max_views, len(near)):
        k = int(np.argmax(dist))
        if dist[k] <= 0:
            break
        chosen.append(near[k])
        dist = np.minimum(dist, np.linalg.norm(look[near] - look[near[k]], axis=1))
    return chosen


def look_at(T_map_cam: np.ndarray | None, reach_m: float = 1.5) -> np.ndarray:
    """The point 1.5 m along a camera's optical axis, in its map frame."""
    if T_map_cam is None:
        return np.zeros(3)
    return T_map_cam[:3, 3] + reach_m * T_map_cam[:3, 2]


def _position(f: FrameRecord) -> np.ndarray:
    return np.zeros(3) if f.T_map_cam is None else f.T_map_cam[:3, 3]


def load_view(rec: Recording, i: int) -> RGBDView:
    f = rec.frames[i]
    if f.depth_path is None or f.T_map_cam is None:
        raise BadRobotData(f"{rec.robot_id}: frame {f.stamp} has no depth or pose")
    return RGBDView(rec.rgb(f), rec.depth(f), rec.intrinsics, f.T_map_cam, f.stamp)


def path_lengths(positions: np.ndarray) -> np.ndarray:
    """The distance travelled (metres) at each of a robot's positions (N, 3), in order."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def path_window(rec: Recording, keyframes: list[int], i: int, length_m: float) -> list[int]:
    """The keyframes within `length_m` of frame i along the robot's path."""
    s = path_lengths(np.array([_position(f) for f in rec.frames]))
    return [k for k in keyframes if abs(s[k] - s[i]) <= length_m]


SECOND_VIEWS = "views along the best overlap's path"


def after_second_views(first: Fit, again: Fit) -> Fit:
    """The fit of a pair refused from its first views and aligned again from the second
    (`local_views`): the second where it merged, its reason saying so; else the first,
    its reason carrying both."""
    if again.merged:
        again.reason += f" ({SECOND_VIEWS})"
        return again
    first.reason += f"; {SECOND_VIEWS}: {again.reason}"
    return first


def local_views(
    overlaps: list[dict],
    rec_a: Recording,
    rec_b: Recording,
    keyframes_a: list[int] | None,
    keyframes_b: list[int] | None,
    max_views: int,
    length_m: float = DEFAULT_VIEWS.local_path_m,
) -> list[tuple[RGBDView, RGBDView]]:
    """The pairs to align again when the first views were refused: each robot's views
    among its keyframes within `length_m` along its path of the best overlap, seeded by
    the overlaps there; [] where that chooses the views `pair_views` chose. A map that
    bends holds one place twice where the robot came back (HoloLens walk, 1 deg/m: A's
    start and end 0.4 m apart), and views of both give the matches one alignment and the
    geometry another. Only from the cascade's verified overlaps: nominated keyframe pairs
    (no verified evidence) get one try, and a link's co-visible pairs count no inliers."""
    overlaps = [o for o in overlaps if o.get("source", "cascade") == "cascade"]
    if not overlaps:
        return []
    best = max(overlaps, key=lambda o: o["inliers"])
    ia, ib = frame_at(rec_a, best["stamp_a"]), frame_at(rec_b, best["stamp_b"])
    kfa = path_window(rec_a, keyframes_a or list(range(len(rec_a))), ia, length_m)
    kfb = path_window(rec_b, keyframes_b or list(range(len(rec_b))), ib, length_m)
    near = [
        o
        for o in overlaps
        if frame_at(rec_a, o["stamp_a"]) in {ia, *kfa}
        and frame_at(rec_b, o["stamp_b"]) in {ib, *kfb}
    ]
    first = select_views(overlaps, rec_a, rec_b, keyframes_a, keyframes_b, max_views)
    chosen = select_views(near, rec_a, rec_b, kfa, kfb, max_views)
    if chosen == first:
        return []
    return _paired(rec_a, rec_b, *chosen)


def _paired(rec_a: Recording, rec_b: Recording, ia: list[int], ib: list[int]) -> list:
    va, vb = _with_depth(rec_a, ia), _with_depth(rec_b, ib)
    return [(x, y) for x in va for y in vb]


def _with_depth(rec: Recording, chosen: list[int]) -> list[RGBDView]:
    """The chosen frames' views but those whose depth image holds no reading (a sensor
    warming up, a covered lens: one such frame failed the whole merge), said once each."""
    views = []
    for i in chosen:
        try:
            views.append(load_view(rec, i))
        except NoDepthReading:
            log.warning("%s: %s has no depth reading: not aligned", rec.robot_id,
                        rec.frames[i].depth_path)  # fmt: skip
    return views


def pair_views(
    overlaps: list[dict],
    rec_a: Recording,
    rec_b: Recording,
    keyframes_a: list[int] | None,
    keyframes_b: list[int] | None,
    max_views: int,
) -> list[tuple[RGBDView, RGBDView]]:
    """The RGB-D pairs to send the aligner for two robots: every selected view of A with
    every selected view of B (`select_views`); [] without a verified overlap."""
    return _paired(
        rec_a, rec_b, *select_views(overlaps, rec_a, rec_b, keyframes_a, keyframes_b, max_views)
    )
