"""The maps' geometry's answer where the raw matches pull a third-look merge elsewhere
(`pinning.pinned_or_refused`): whether the geometry leads back from the matches' place to the
merge (`falls_back`: the pull does not refuse it), or merges at that place too (`follow`:
the merge moves there)."""

from __future__ import annotations

import numpy as np

from fleetmap.align.geometric_look import (
    firm_at_floor,
    firm_at_noise,
    judge,
    look_voxel,
    merged,
    refine,
)
from fleetmap.align.hypotheses import once, probe_points
from fleetmap.align.types import AlignParams, AlignResult
from fleetmap.geometry import displacement_rms


def falls_back(T_near: np.ndarray, T: np.ndarray, pair, p: AlignParams, depth: float) -> bool:
    """Whether the maps' geometry leads back from an alignment T_near that the matches
    prefer near a merge T (`pinning.pinned_or_refused`). ICP from T_near (`refine`,
    point-to-plane at half the look's voxel) lands within the map's own voxel (`voxel_m`) of
    T, and T_near's firm free-space consistency (`firm_at_noise`) is under the first look's
    bar (`min_consistency`, 0.7, the laxest the gate asks) or under T's own; or T_near is
    under that bar and ICP from it lands where the free space is not firm under the look's
    own bar (`firm_at_floor`): no place this look would merge.

    Where the surfaces slide along each other (what the matches' pinning guards against), an
    alignment along the slide keeps its free space and ICP leaves it near where it is: a
    HoloLens pair through a D435's noise merged 11.8 cm off, the matches preferring an
    alignment 13 cm away at firm 0.89 whose refinement lands 7 cm from the merge; SUN3D
    windows 10.6 cm off, the pull at firm 0.82, its refinement 21 cm away; another HoloLens
    pair through that noise, 6.4-7.0 cm off, the pull at firm 0.84-0.88, its refinement just
    beyond the voxel. At a right merge (HoloLens, 18% shared, 2.9 cm) the matches preferred
    one 21 cm off at firm 0.52-0.58 (ten pairs of map frames), whose refinement lands 5-19
    mm from the merge (docs/ALIGNER.md, session 34). A HoloLens pair at 0.4 of its size,
    B another camera, merged 3.0-4.3 cm off (firm 0.96-0.97 at the noise, the truth's
    too), had the matches prefer one 55 cm off at firm 0.21-0.25 whose refinement slid
    17-27 cm off, to firm 0.51 (no noise floor) or 0.85 (at it) (session 40).

    A pull whose place passes the first look's bar but is less firm than the merge, and from
    which ICP returns to the merge, is no slide either: along a slide ICP stays. A HoloLens
    pair (51% shared) at 1.5 times its size through a D435's noise passed the look 4.6 cm
    off (firm 0.92), and 17 raw matches against 11 preferred an alignment 16 cm away, 12 cm
    from the truth, at firm 0.83, whose refinement lands 0-1.7 cm from the merge; it was
    refused (docs/ALIGNER.md, session 55)."""
    firm_near = firm_at_noise(T_near, pair, p, depth)
    voxel, clouds = look_voxel(p, depth), pair.clouds()
    probe = probe_points(clouds[1].at(voxel))
    T_back = refined(T_near, pair, voxel)
    if displacement_rms(T_back, T, probe) < p.voxel_m:
        return firm_near < p.min_consistency or firm_near < firm_at_noise(T, pair, p, depth)
    if firm_near >= p.min_consistency:
        return False
    return firm_at_floor(T_back, pair, p, depth) < p.geometric.min_consistency


def follow(T_near: np.ndarray, pair, p: AlignParams, depth: float) -> AlignResult | None:
    """The look's merge moved to where the raw matches pull it (`pinning.pinned_or_refused`):
    the alignment they prefer near the merge, refined as a basin is (`refine`) and judged as
    the look judges (`judge`); None where it does not pass. Not refined further as `settle`
    refines: there the depth leads back to where the geometry led. Through a D435's noise a
    HoloLens pair (51% shared) passed the look 7.2 cm off, where 28 raw matches agreed with
    an alignment 9 cm from it against 20: that alignment, 3.6 cm from the truth, refined
    lands 1.7 cm from it and passes (firm 0.98, grey levels 0.77), and no alignment nearby
    is preferred there; `settle`'s refinement of it slid back to the 7.2 cm (docs/ALIGNER.md,
    session 53)."""
    look, voxel = p.geometric, look_voxel(p, depth)
    clouds, floor = pair.clouds(), pair.noise_floor(look.noise_k)
    moved = judge(refined(T_near, pair, voxel), clouds, pair.seen(), voxel, floor)
    if not moved.passes(look, p):
        return None
    return merged(moved, "fpfh+icp+matches", "moved where the raw matches agree")


def refined(T_near: np.ndarray, pair, voxel: float) -> np.ndarray:
    """`refine` of the pull's place, once per place in the pair's memo: `falls_back` asks it
    first, and `follow` starts from it where the pull did not fall back."""
    return once(pair.memo, "pull", T_near, lambda T: refine(T, pair.clouds(), voxel))
