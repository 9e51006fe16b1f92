"""The live merge worker's views of a robot pair: the stored RGB-D views near the pair's
verified keyframes, chosen as `fleetmap merge` chooses them (`view_choice.spread`), and,
when the gate refused those, the views along both robots' paths near the best overlap
(as `view_choice.local_views`: a map that bends holds one place twice)."""

from __future__ import annotations

import numpy as np

from fleetmap.fleet.types import DEFAULT_VIEWS
from fleetmap.fleet.view_choice import look_at, path_lengths, spread
from fleetmap.view import stored_view


class StoredViews:
    """Keyframe poses read once (they never change) and the views chosen from them."""

    def __init__(self, db):
        self.db = db
        self._poses: dict[int, np.ndarray] = {}  # keyframe id -> T_map_cam

    def pose(self, kf_id: int) -> np.ndarray:
        if kf_id not in self._poses:
            self._poses[kf_id] = self.db.load_frame(kf_id).T_map_cam
        return self._poses[kf_id]

    def choose(self, robot: str, seeds: list[int], max_views: int, within=None) -> list[int]:
        """The robot's keyframe ids to align (with a stored view): the verified keyframes
        `seeds` first, spread as in a batch merge; only among `within` if given."""
        with_view = self.db.view_ids(robot)
        if within is not None:
            with_view = [k for k in with_view if k in within]
        have = set(with_view)
        seed = [k for k in dict.fromkeys(seeds) if k in have]
        if not seed:
            return []
        cand = list(dict.fromkeys(seed + with_view))
        look = np.array([look_at(self.pose(k)) for k in cand])
        return sorted(cand[i] for i in spread(len(seed), look, max_views))

    def along_path(self, robot: str, kf_id: int, length_m: float) -> set[int]:
        """The robot's keyframes within `length_m` of keyframe `kf_id` along its path."""
        ids = self.db.keyframe_ids(robot)
        if kf_id not in ids:
            return set()
        s = path_lengths(np.array([self.pose(k)[:3, 3] for k in ids]))
        at = s[ids.index(kf_id)]
        return {k for k, d in zip(ids, s, strict=True) if abs(d - at) <= length_m}

    def local(self, a: str, b: str, ranked: list, max_views: int, first: list[list[int]]):
        """(A's ids, B's ids) along both paths near the best overlap (`ranked[0]`), seeded
        by the overlaps there; None where those are the views `first` chosen."""
        best, length = ranked[0], DEFAULT_VIEWS.local_path_m
        near_a = self.along_path(a, best.kf_a, length) | {best.kf_a}
        near_b = self.along_path(b, best.kf_b, length) | {best.kf_b}
        seeds = [o for o in ranked if o.kf_a in near_a and o.kf_b in near_b]
        ids = [
            self.choose(a, [o.kf_a for o in seeds], max_views, near_a),
            self.choose(b, [o.kf_b for o in seeds], max_views, near_b),
        ]
        return None if ids == first or not all(ids) else ids

    def load(self, ids: list[int]) -> list:
        """The stored views of the keyframes (`RGBDView`s)."""
        return [stored_view(self.db.load_frame(k), *self.db.view_bytes(k)) for k in ids]
