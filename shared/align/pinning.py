"""Whether the matches pin a merge the maps' geometry proposed, or pull it elsewhere.

A merge that rests on the maps' geometry (the first look's where the free space decided
alone, the second look's, the third look's) can slide along surfaces that slide along each
other while the free space stays consistent. The raw matches say where they agree: a merge
is refused where they prefer an alignment nearby (`unpinned`) or, for the third look, where
the verified matches agree on one far away (`outvoted`). For the third look the maps'
geometry has its say on the pull: a place it refuses, or holds less firmly than the merge,
and leaves for the merge (`pulls.falls_back`) does not refuse it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fleetmap.align.hypotheses import beyond_rivals, rigid_hypotheses
from fleetmap.align.types import AlignParams, AlignResult
from fleetmap.align.validation import better_nearby, distinct, outnumbers
from fleetmap.correspondences import Correspondences
from fleetmap.geometry import displacement_rms, residuals

#: `falls_back(T_near, T)` (`pulls.falls_back` on the pair): whether the maps'
#: geometry leads back to a merge T from the alignment the matches prefer near it
FallsBack = Callable[[np.ndarray, np.ndarray], bool]

#: `follow(T_near)` (`pulls.follow` on the pair): the look's merge moved to the
#: alignment the matches prefer nearby, or None where the look would not merge it there
Follow = Callable[[np.ndarray], AlignResult | None]


def carried(decisive: bool, T: np.ndarray, R: Correspondences, p: AlignParams) -> bool:
    """Did the geometry carry a first-look merge on its own: decisive free space, and
    fewer matches within the RANSAC tolerance of T itself than the gate asks of a merge the
    geometry does not decide? Such a merge must be pinned (`pipeline._align`): surfaces
    that slide along each other keep the free space consistent (SUN3D windows 27 cm off at
    firm 0.99, 7 matches at the merge, 24 at an alignment 24 cm away; the whole
    recordings, right at firm 0.995, have 49 at theirs: docs/ALIGNER.md, session 23)."""
    return decisive and int(np.count_nonzero(residuals(T, R.X, R.Y) < p.ransac_tol_m)) < (
        p.min_inliers
    )


def unpinned(
    T: np.ndarray,
    R: Correspondences,
    probe: np.ndarray,
    p: AlignParams,
    floor: int = 0,
    back: FallsBack | None = None,
) -> tuple[str, np.ndarray | None]:
    """Why the matches do not pin T (`validation.better_nearby`: more of them agree with an
    alignment nearby), and that alignment; ("", None) where they pin it. With a `floor`,
    those that agree there must be at least that many distinct places (`validation.distinct`
    at the voxel): a handful of places, each matched several times, is still a handful.
    With `back`, a place the maps' geometry refuses and leads back from to T does not
    count."""
    found = better_nearby(T, R.X, R.Y, probe, p.ransac_tol_m, p.rival_m)
    if found is None:
        return "", None
    T_near, n, n_T = found
    agree = residuals(T_near, R.X, R.Y) < p.ransac_tol_m
    if floor and distinct(R.X, R.Y, agree, p.voxel_m) < floor:
        return "", None
    if back is not None and back(T_near, T):
        return "", None
    return (
        f"the matches agree better with an alignment {displacement_rms(T_near, T, probe):.2f} m "
        f"away ({n} against {n_T} within {p.ransac_tol_m:.2f} m): the maps' geometry alone "
        "led here (surfaces that slide along each other?)"
    ), T_near


def pinned_or_refused(
    third: AlignResult,
    R: Correspondences,
    probe: np.ndarray,
    p: AlignParams,
    C: Correspondences | None = None,
    back: FallsBack | None = None,
    follow: Follow | None = None,
) -> AlignResult:
    """The third look's merge, refused where the matches do not pin it (`unpinned`), as the
    second look's, where the alignment they prefer gathers at least half `min_inliers`
    distinct places (what a merge the geometry decides needs of them, `pipeline._align`; a
    right HoloLens merge, 3.5 cm, was refused by 8 matches at four places, session 33): a
    handful agreeing by chance, among thousands of raw matches on a few surfaces, does not
    overrule the geometry. Right third-look merges of the recall bench (1-15 of 1,400-2,200
    raw matches at the truth) had no alignment nearby that more agree with. Where the depth
    is noisy the geometry slides along its planes: a HoloLens pair (35% shared) seen through
    an active-stereo camera's noise (`simulate.stereo_depth_noise` at the D435's level, 2.6
    cm at its 2.7 m) passed free space and colour 12 cm off, while 27 matches agreed with an
    alignment 13 cm from it (10 from the truth) against 9 with it (docs/ALIGNER.md, session
    26). `C`, the verified matches: refused too where they agree on an alignment far from it
    (`outvoted`). `back` (`pulls.falls_back` on the pair): a pull to a place the
    maps' geometry refuses and leads back from to the merge does not refuse it (a HoloLens
    pair, 18% shared, merged about 3 cm from the truth, was refused through session 33 by
    12 raw matches at seven places agreeing with an alignment 21 cm off, whose firm free
    space is 0.55 and from which ICP returns to within 7 mm of the merge; docs/ALIGNER.md,
    session 34). `follow` (`pulls.follow` on the pair): where the matches pull the
    merge to a place nearby that the look would merge too and that they pin in turn, the
    merge moves there instead of being refused (`moved_by_pull`; session 53)."""
    if not third.merged:
        return third
    why, moved = moved_by_pull(third.T_a_b, R, probe, p, follow, p.min_inliers // 2, back)
    third = moved or third
    T = third.T_a_b
    why = why or (outvoted(T, C, probe, p) if C is not None else "")
    if why:
        third.merged, third.reason = False, f"{third.reason}, but {why}"
    return third


def moved_by_pull(
    T: np.ndarray,
    R: Correspondences,
    probe: np.ndarray,
    p: AlignParams,
    follow: Follow | None,
    floor: int = 0,
    back: FallsBack | None = None,
) -> tuple[str, AlignResult | None]:
    """Why the matches do not pin T (`unpinned`; "" where they do), or, where they pull it to
    a place nearby that `follow` merges and that they pin in turn, ("", that merge), its
    reason naming the pull."""
    why, T_near = unpinned(T, R, probe, p, floor, back)
    moved = follow(T_near) if why and follow is not None else None
    if moved is None or not moved.merged or unpinned(moved.T_a_b, R, probe, p, floor, back)[0]:
        return why, None
    led = displacement_rms(moved.T_a_b, T, probe)
    moved.reason += f"; the maps' geometry led {led:.2f} m from here, where {why.split(':')[0]}"
    return "", moved


def outvoted(T: np.ndarray, C: Correspondences, probe: np.ndarray, p: AlignParams) -> str:
    """Why the verified matches (of view pairs that passed the epipolar check) refuse a
    merge the maps' geometry proposed, for an alignment far from it, or "": a consensus of
    at least `min_inliers` of them (the first look's pooled hypotheses), beyond the gate's
    rivals from T, that more of them agree with than with T, beyond the noise of the two
    counts. The first look may refuse the right alignment on its free space (a HoloLens
    revisit at 1.5 times its size: 119 of 235 verified matches at the truth, consistency
    0.64), and the third look then found a basin 3.6 m away that no match agrees with,
    with clean free space and grey levels correlating 0.57 (docs/ALIGNER.md, session 32).
    Raw matches would not do: 12 of 494 (three times chance) agree with an alignment 4.6 m
    from a right third-look merge. `unpinned` looks only nearby."""
    if len(C) < p.min_inliers:
        return ""
    n_T = int(np.count_nonzero(residuals(T, C.X, C.Y) < p.ransac_tol_m))
    for h in rigid_hypotheses(C, p, p.min_inliers):
        far = beyond_rivals(h.T_a_b, T, probe, p)
        if far and outnumbers(h.support, n_T):
            return (
                f"{h.support} verified matches agree with an alignment {far} away, {n_T} with "
                f"it (within {p.ransac_tol_m:.2f} m)"
            )
    return ""
