"""The merge worker's rules, pure functions of the stored state: when a pair is due, in
which order due pairs go (fair: no pair can stay first by gaining evidence), and which
robot is the reference (not one a newcomer wins by arriving first).

A refused pair is due again only once its evidence grew by `retry_factor` (and at least
`retry_min_new` overlaps) and its back-off since the last attempt has passed, doubling
with each refusal up to `retry_backoff_max_s`: however fast a robot posts, its pair costs
the aligner a bounded number of attempts. Due pairs go in order: those that place a new
robot first, then the one tried longest ago (never tried first), then by evidence.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fleetmap.fleet.types import PairState, edge, state_transform

#: Views a robot that judge a refit against the fit it would replace (`refit_or_kept`):
#: about 1-2 s of decoding for both robots, at most a few times per pair.
WHOLE_MAP_VIEWS = 40


def is_due(st: PairState | None, n: int, p, quiet: bool, views_changed: bool, now: float) -> bool:
    """Whether a pair with state `st` (None: never tried) and `n` verified overlaps is due
    (`p`: `LiveParams`; `now`: unix time, as `st["at"]`)."""
    if st is None:
        return True
    if st["status"] == "merged":
        if quiet and (n > st["evidence"] or st.get("budget", p.max_views) < p.max_views):
            return True  # the robots went quiet: a last fit on every overlap and view
        return n >= max(st["evidence"] * p.refine_factor, st["evidence"] + p.refine_min_new)
    if st["status"] == "no_views":
        return views_changed
    if now - st.get("at", 0.0) < backoff_s(st, p):
        return False
    if quiet and st.get("budget", p.max_views) < p.max_views:
        return True  # refused on the first, smaller fit: once more with every view
    return n >= max(st["evidence"] + p.retry_min_new, np.ceil(st["evidence"] * p.retry_factor))


def refit_or_kept(before: PairState | None, new: PairState, views: Callable[[], list]) -> PairState:
    """A pair's state after a gated fit: the new fit, unless it replaces a merge and fits
    the two robots' surfaces worse than the transform it would replace. Both are measured
    by the aligner's own depth-alone `surface_rmse` on the robots' whole maps (`views()`:
    A's and B's, `whole_map_views`), not on the refit's views: the aligner chose the refit
    by that measure on those, so there it always wins. A worse refit leaves the earlier fit
    in place, the attempt counted. Last fits never end worse (issue 23)."""
    if before is None or before["status"] != "merged":
        return new
    old_m, new_m = surface_rmses(views(), [before["transform"], new["transform"]])
    if new_m <= old_m:
        return new | {"surface_rmse_m": new_m}
    keep = {k: new[k] for k in ("evidence", "attempts", "budget", "since")}
    why = f"a refit sat {new_m:.4f} m from the surfaces of the whole maps, this fit {old_m:.4f}"
    return before | keep | {"kept": why, "surface_rmse_m": old_m}


def whole_map_views(db, robot: str, n: int = WHOLE_MAP_VIEWS) -> list:
    """The robot's stored views (`StoredView`), evenly thinned to at most `n`."""
    from fleetmap.view import stored_view

    ids = db.view_ids(robot)
    step = max(1, -(-len(ids) // n))
    return [stored_view(db.load_frame(k), *db.view_bytes(k)) for k in ids[::step]]


def robot_order(db, robots: list[dict] | None = None) -> list[str]:
    """Robot names in order of arrival (their store codes)."""
    names = [r["robot_id"] for r in (db.robots() if robots is None else robots)]
    codes = {n: db.robot_code(n) for n in names}
    return sorted((n for n in names if codes[n] is not None), key=lambda n: codes[n])


def new_merge(st: PairState) -> bool:
    """Whether a stored pair state is a fit just made (to register as a link): not a
    refusal or worse refit that kept an earlier merge."""
    return (
        st["status"] == "merged" and bool(st.get("at")) and not {"last_refusal", "kept"} & set(st)
    )


def surface_rmses(views: list, transforms: list) -> list[float]:
    """`fleetmap.align.surface_rmse` of B's views' cloud on A's under each T_a_b, at the
    aligner's fine voxel (`views`: A's, B's; stored or decoded views)."""
    from fleetmap.align import surface_rmse
    from fleetmap.align.types import AlignParams
    from fleetmap.mapcloud import views_cloud

    v = AlignParams().voxel_m
    ca, cb = (
        views_cloud(
            [x.decoded() if hasattr(x, "decoded") else x for x in side], v, with_color=False
        )
        for side in views
    )
    return [surface_rmse(cb, ca, np.asarray(T, np.float64), v) for T in transforms]


def nominated_pairs(states: dict, verified: set[str], counts: dict, skip: set) -> list:
    """Robot pairs (a, b) to align from nominated keyframe pairs once the robots are quiet:
    both with keyframes, none in `skip`, no verified overlap between them, not merged, and
    not tried on nominations since either robot's keyframe count changed (`counts`: robot
    -> keyframes; a pair's state keeps the counts it was tried at, "nominated")."""
    names = sorted(r for r, n in counts.items() if n and r not in skip)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            key = "|".join((a, b))
            st = states.get(key)
            if key in verified or (st is not None and st["status"] == "merged"):
                continue
            if st is None or st.get("nominated") != [counts[a], counts[b]]:
                out.append((a, b))
    return out


def backoff_s(st: dict, p) -> float:
    """How long a refused pair waits after its last attempt: doubling per refusal."""
    refusals = max(1, st.get("refusals", 1))
    return min(p.retry_backoff_s * 2.0 ** (refusals - 1), p.retry_backoff_max_s)


def due_order(joins: bool, st: dict | None, n: int, a: str, b: str) -> tuple:
    """Sort key of a due pair with `n` verified overlaps (0: nominated by the bags of words
    alone): verified evidence first, then new robots, then round-robin by last attempt,
    then the most evidence. Nominated pairs come last because they are mostly refused, at
    18-30 s each: when the robots went quiet the merged pairs' last fits used to wait behind
    them (`bench/live_stream.py`: three nominated pairs of a robot from another building,
    then the last fits at 137-145 s)."""
    return (n == 0, not joins, 0.0 if st is None else st.get("at", 0.0), -n, a, b)


def reference(names: list[str], edges: dict, counts: dict | None = None) -> str | None:
    """The reference robot: of the largest merged group, the robot with the most
    keyframes, ties by name. Arriving first wins nothing, and the same stored state gives
    the same reference on every replica and after a restart."""
    if not names:
        return None
    counts = counts or {}
    group = {n: {n} for n in names}
    for a, b in edges:
        joined = group[a] | group[b]
        for n in joined:
            group[n] = joined
    size = max(len(g) for g in group.values())
    return min((n for n in names if len(group[n]) == size), key=lambda n: (-counts.get(n, 0), n))


def merged_edges(states: dict[str, PairState], names: set[str]) -> dict:
    """(A, B) -> `edge` of every merged pair whose robots are in `names`."""
    edges = {}
    for st in states.values():
        if st["status"] != "merged":
            continue
        a, b = st["robot_a"], st["robot_b"]
        if a in names and b in names:
            edges[(a, b)] = edge(state_transform(st), st["inliers"])
    return edges


def same_picture(fa, fb, tol_px: float = 0.5, share: float = 0.9) -> bool:
    """Whether two frames (`fleetmap.frame.Frame`) are one picture posted twice: of the
    same size, with `share` of the features of each at the same pixel (within `tol_px`).
    Two cameras, or one camera twice, never put 90% of their MSER regions on the same
    pixels unless the picture is the same; such a keyframe is no second look at a place."""
    from scipy.spatial import cKDTree

    if (fa.width, fa.height) != (fb.width, fb.height) or min(
        len(fa.keypoints), len(fb.keypoints)
    ) < 20:
        return False
    for x, y in ((fa.keypoints, fb.keypoints), (fb.keypoints, fa.keypoints)):
        d, _ = cKDTree(y).query(x, distance_upper_bound=tol_px)
        if np.mean(np.isfinite(d)) < share:
            return False
    return True


def evidence(db, a: str, b: str, same: dict, copied: dict) -> list:
    """The pair's cascade overlaps that are a second look at a place, not one picture
    posted by both (`same_picture`, cached in `same` per keyframe pair); each copy (the
    later keyframe) is noted in `copied`: robot -> {keyframe: the robot it repeats}."""
    out = []
    for o in db.overlaps(a, b):
        if o.source != "cascade":
            continue
        key = (o.kf_a, o.kf_b)
        if key not in same:
            same[key] = same_picture(db.load_frame(o.kf_a), db.load_frame(o.kf_b))
        if not same[key]:
            out.append(o)
            continue
        copier, kf, other = (b, o.kf_b, a) if o.kf_b > o.kf_a else (a, o.kf_a, b)
        copied.setdefault(copier, {})[kf] = other
    return out


def copier_robots(copied: dict, counts: dict) -> dict[str, str]:
    """{robot: reason} of robots at least half of whose keyframes repeat other robots'
    pictures: they bring no observation of their own and are not placed (fewer copies are
    only left out of the evidence)."""
    return {
        r: f"{len(kfs)} of its {counts[r]} keyframes repeat the pictures of "
        f"{', '.join(sorted(set(kfs.values())))}: no evidence of where it is"
        for r, kfs in copied.items()
        if r in counts and 2 * len(kfs) >= counts[r]
    }
