"""Nominated keyframe pairs: where to look for two robots' common place when the cascade
verified none.

The cascade verifies a keyframe pair on its own: a GIST neighbour, then enough epipolar
inliers among the keyframes' few hundred features. Revisits from another direction fail
both (the HoloLens walk: windows sharing half their surfaces, no pair verified). Measured
on such a pair, the keyframe structures hold too little for any keyframe-level test: about
250 features a keyframe, 41% with depth, and at most 6 matches agreeing with the true
transform in the best pair, none at all for half the keyframes; a robot-pair consistency
search over 3D RANSAC proposals of 320 candidate pairs found 2 proposals. But the bag of
words still ranks the right keyframe first (Bhattacharyya distance, the whole robot pair
scored at once), and the aligner, with 1,000 features per full view, per-pair rigid
hypotheses and its free-space gate, merges the pair within 1.2 cm from the views around
the four BoW-nearest pairs.

So a robot pair with no verified overlap is given its BoW-nearest keyframe pairs, distinct
keyframes on each side, as nominations (source "nominated"). They are not overlaps: they
are where the aligner looks, and the aligner's gate decides, refusing rather than guessing.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

NOMINATED = 4  # keyframe pairs nominated per robot pair: the aligner spreads views around them


def nominate(
    ids_a: list[int], ids_b: list[int], bow_distances: Callable, k: int = NOMINATED
) -> list[tuple[int, int, float]]:
    """The `k` BoW-nearest keyframe pairs (a, b, distance) between two robots, nearest
    first, no keyframe used twice, none without a visual word in common.
    `bow_distances(kf, others)` -> distances, shape (len(others),)."""
    scored: dict[tuple[int, int], float] = {}
    for mine, others, flip in ((ids_b, ids_a, False), (ids_a, ids_b, True)):
        if not others:
            return []
        for kf in mine:
            d = bow_distances(kf, others)
            j = int(np.argmin(d))
            if d[j] < 1.0:  # 1: not one visual word in common
                pair = (kf, others[j]) if flip else (others[j], kf)
                scored[pair] = float(d[j])
    out, used_a, used_b = [], set(), set()
    for (a, b), d in sorted(scored.items(), key=lambda x: x[1]):
        if a not in used_a and b not in used_b:
            out.append((a, b, d))
            used_a.add(a)
            used_b.add(b)
        if len(out) == k:
            break
    return out


def nominated_overlaps(db, robot_a: str, robot_b: str, k: int = NOMINATED) -> list:
    """`nominate` between two robots of a `PlaceDB`, as overlaps with source "nominated"
    (no inliers: nothing was verified)."""
    from fleetmap.errors import BadInput
    from fleetmap.place.types import Overlap

    if robot_a == robot_b:  # each keyframe was nominated with itself
        raise BadInput(
            "Nominations pair two robots; a robot's own revisits are its overlaps with "
            "source 'cascade'"
        )
    for r in (robot_a, robot_b):
        db._code(r)  # UnknownRobot for a robot deleted meanwhile
    ids_a, ids_b = db.keyframe_ids(robot_a), db.keyframe_ids(robot_b)
    frames: dict = {}

    def load(kf: int):
        if kf not in frames:
            frames[kf] = db.load_frame(kf)
        return frames[kf]

    def bow(kf: int, others: list[int]) -> np.ndarray:
        f = load(kf)
        return db.index.bow_distances(f.bow_ids, f.bow_counts, np.array(others))

    return [
        Overlap(robot_a, a, load(a).stamp, robot_b, b, load(b).stamp, 0, 0, "nominated")
        for a, b, _ in nominate(ids_a, ids_b, bow, k)
    ]
