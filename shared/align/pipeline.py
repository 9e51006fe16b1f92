"""The default alignment of two robots' maps from matched RGB-D pairs, with a quality gate.

1. Pool 3D-3D correspondences over the pairs (`fleetmap.correspondences`).
2. Rigid hypotheses by sequential RANSAC: the best consensus, then the best among what is
   left, and so on. Look-alike places (rows of identical cubicles) give consistent but
   wrong consensus sets, so the largest one is not trusted blindly.
3. Each hypothesis refined by point-to-plane ICP on the two robots' map clouds and scored
   by geometric overlap; the best wins.
4. The gate: enough inlier correspondences, enough spread, a small held-out residual (each
   fold of inliers predicted by a fit on the others), and no rival hypothesis far away with
   nearly the same overlap. Otherwise: no merge, with the reason.
5. An MLP (the thesis's estimator) on the inliers, kept only where it lowers the held-out
   error of the rigid fit.
6. Refused: a second look with affine-simulated SIFT on a few views of each robot
   (`fleetmap.align.second_look`), its matches judged with the first's by the same gate.
7. Refused again: a third look on the maps' geometry alone, judged by free space and colour
   (`fleetmap.align.geometric_look`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from fleetmap.align.geometric_look import firm_at_floor, geometric_look, unfirm
from fleetmap.align.hypotheses import (
    choose,
    consistency_at_noise,
    once,
    pair_hypotheses,
    probe_points,
    raw_hypotheses,
    rigid_hypotheses,
)
from fleetmap.align.pinning import carried, moved_by_pull, pinned_or_refused
from fleetmap.align.pulls import falls_back, follow
from fleetmap.align.second_look import affine_matches
from fleetmap.align.surfaces import grey_correlation
from fleetmap.align.types import DEFAULT_ALIGN, AlignParams, AlignResult, unique_views
from fleetmap.align.validation import holdout_residual, spread_m
from fleetmap.correspondences import Correspondences, RGBDView, pair_features, verified_and_raw
from fleetmap.depth_noise import DepthNoise
from fleetmap.errors import BadInput
from fleetmap.estimators import MLPEstimator
from fleetmap.geometry import apply, displacement_rms, invert, residuals, transform_error
from fleetmap.mapcloud import SeenDepth, ViewsCloud, overlap_fitness
from fleetmap.registration import kabsch

log = logging.getLogger(__name__)


def align_views(
    pairs: list[tuple[RGBDView, RGBDView]],
    p: AlignParams = DEFAULT_ALIGN,
) -> AlignResult:
    """Fit T_a_b from RGB-D pairs (view of robot A, view of robot B); gate it.

    Views shared by several pairs (the same object) are processed once."""
    t0 = time.perf_counter()
    if not pairs:
        raise BadInput("Give at least one RGB-D pair")
    depth = scene_depth(pairs)
    p = p.at_depth(depth)  # a nearer or farther scene: every length in proportion
    C, R = verified_and_raw(pairs, pair_features(pairs))
    # both looks see the same views: their clouds made once
    pair = _PairClouds(pairs, p.max_depth_m, (p.cloud_depth_cap(depth), p.coarse_voxel_m))
    res = _align(C, R, pair, p, depth)
    if not res.merged and p.second_look and len(R) >= p.min_inliers:
        R = Correspondences.concat([R, affine_matches(pairs, len(pairs), p.second)])
        again = _align(C, R, pair, p, depth, pinned=True)
        if again.merged and p.use_icp:
            why = unfirm(again.T_a_b, pair, p, depth)
            again.merged, again.reason = not why, why or again.reason
        if again.merged:
            res = again
            res.method += "+asift"
        else:
            res.reason += f"; with affine-simulated features too: {again.reason}"
    if not res.merged and p.use_icp and p.geometric_look:
        probe = probe_points(pair.clouds()[1].at(p.coarse_voxel_m, normals=False))
        back = lambda T_near, T: falls_back(T_near, T, pair, p, depth)  # noqa: E731
        move = lambda T_near: follow(T_near, pair, p, depth)  # noqa: E731
        third = pinned_or_refused(geometric_look(pair, p, depth), R, probe, p, C, back, move)
        if third.merged:
            res = third
        else:
            res.reason += f"; on the maps' geometry: {third.reason}"
    res.correspondences, res.scene_depth_m = len(R), depth
    res.seconds = time.perf_counter() - t0
    log.info(
        "alignment: merged=%s (%s), %d correspondences, %.1f s",
        res.merged,
        res.reason,
        len(R),
        res.seconds,
    )
    return res


def scene_depth(pairs: list[tuple[RGBDView, RGBDView]]) -> float:
    """Median depth (metres) of the pairs' views: the median of each distinct view's
    median reading (every 16th pixel)."""
    views = {id(v): v for pr in pairs for v in pr}.values()
    meds = []
    for v in views:
        d = v.depth[::4, ::4]
        d = d if d.any() else v.depth
        meds.append(float(np.median(d[d > 0])) / v.intrinsics.depth_scale)
    return float(np.median(meds))


class _PairClouds:
    """Each robot's views (`unique_views`) and their clouds (`ViewsCloud`, made on first
    use and kept with every scale they were asked at), for both looks at one pair; `memo`:
    `hypotheses.choose`'s ICPs and judgements on them, which the second look meets again
    for the first look's hypotheses."""

    def __init__(self, pairs, max_depth: float = DEFAULT_ALIGN.max_depth_m, reach=None):
        """Readings farther than `max_depth` (metres) are left out; `reach` (farthest,
        bound): farther, up to `farthest`, as far as the robots' readings agree within
        `bound` (`_reach`)."""
        self.views = unique_views(pairs, 0), unique_views(pairs, 1)
        self.max_depth, self._noise = max_depth, None
        if reach is not None and reach[0] > max_depth:
            self.max_depth, noise = _reach(self.views, max_depth, *reach)
            if self.max_depth == reach[0]:  # measured to where the clouds reach: keep it
                self._noise = noise
        self._clouds = self._seen = None
        self.memo: dict = {}

    def clouds(self) -> tuple[ViewsCloud, ViewsCloud]:
        if self._clouds is None:
            self._clouds = tuple(ViewsCloud(v, max_depth=self.max_depth) for v in self.views)
        return self._clouds

    def seen(self) -> tuple[list[SeenDepth], list[SeenDepth]]:
        """Each robot's views as `SeenDepth` (their nearest-reading images made once, for
        the third look's judging and the pinning's)."""
        if self._seen is None:
            self._seen = tuple([SeenDepth(v) for v in views] for views in self.views)
        return self._seen

    def noise_floor(self, k: float):
        """The third look's free-space margin at each depth read (metres -> metres): k
        times the spread between one robot's reading and the other's (`DepthNoise`,
        measured on each robot's views once); None where k is 0."""
        if not k:
            return None
        if self._noise is None:
            a, b = (DepthNoise.measure(v, max_depth=self.max_depth) for v in self.views)
            self._noise = a.between(b)
        noise = self._noise
        return lambda depth: k * noise(depth)


def _reach(views, near: float, far: float, bound: float) -> tuple[float, DepthNoise]:
    """How far (metres, from `near` to `far`) the clouds reach: up to the first depth where
    the two robots' own readings disagree by more than `bound`; and that disagreement
    (`DepthNoise.between`, measured to `far`). Far
    readings help where the sensor still measures there and hurt where it does not: the
    HoloLens walk at twice its size (median depth 5.1 m) agrees within 3.2 cm out to 12 m
    and merges only with them; SUN3D's Xtion spreads 13 cm at 6 m, and its study room
    (median 3.3 m) merged 8.7 -> 15.6 cm from the truth with readings to 6.6 m
    (docs/ALIGNER.md, session 43). `DepthNoise` measures in bands to 7 m (`EDGES`) and
    holds its last band's spread (5.5-7 m) beyond: past it the reach is what that band
    allows, not a measurement."""
    a, b = (DepthNoise.measure(v, max_depth=far) for v in views)
    noise = a.between(b)
    depths = np.append(np.arange(near, far, 0.25), far)
    over = np.flatnonzero(noise(depths) > bound)
    return (float(depths[over[0]]) if len(over) else far), noise


def _align(
    C: Correspondences,
    R: Correspondences,
    pair: _PairClouds,
    p: AlignParams,
    depth: float,
    pinned=False,
) -> AlignResult:
    """C: verified (epipolar) correspondences, R: raw matches of every pair. `pinned`: the
    matches must pin the fit (`pinning.unpinned`), asked of the second look's merges: they
    rest on the maps' geometry started from a few ASIFT matches (moved where the matches
    pull them, where the third look merges: `pinning.moved_by_pull`). Not of the first look's,
    where the refinement already follows the matches (`hypotheses.ranked`) and where a
    robot's map that bends is fitted as a whole a few centimetres off where the matched
    views are (`agreeing`: HoloLens walk with 1 deg/m of drift, 65 matches agree with a fit
    13 cm away, 11 with the merge, which holds there within the test's 15 cm); unless the
    geometry carried it alone (`pinning.carried`)."""
    if len(R) < p.min_inliers:
        return AlignResult(
            False, f"only {len(R)} correspondences with depth (need {p.min_inliers})"
        )
    hyps = rigid_hypotheses(C, p) if len(C) >= p.min_inliers else []
    hyps += pair_hypotheses(R, p)
    if pinned and p.raw_consensus:  # opt-in: `hypotheses.raw_hypotheses`
        hyps += raw_hypotheses(R, p)
    if not hyps:
        return AlignResult(False, "no rigid consensus among the correspondences")
    (views_a, views_b), clouds = pair.views, pair.clouds()
    noisy = lambda T: at_noise(T, pair, depth, p)  # noqa: E731
    if p.use_icp:
        best, rivals = choose(hyps, R, views_a, views_b, clouds, p, pair.memo, noisy)
        probe = probe_points(clouds[1].at(p.coarse_voxel_m, normals=False))
        method = "rigid+icp+colour" if best.source.endswith("+colour") else "rigid+icp"
    else:
        best, rivals, probe = max(hyps, key=lambda h: h.support), [], None
        method = "rigid"
    inl = agreeing(best.T_a_b, R, p.ransac_tol_m)
    out = AlignResult(False, "", best.T_a_b, method, inliers=int(inl.sum()), fitness=best.fitness)
    out.hypotheses = [h.summary() for h in [best, *rivals]]
    decisive = p.use_icp and _decisive(best, clouds, p)
    need = p.min_inliers // 2 if decisive else p.min_inliers
    out.reason = (
        _geometry_gate(best, rivals, p, probe, decisive, noisy) if p.use_icp else ""
    ) or _match_gate(out, R, inl, p, p.spread_needed(depth), need)
    if not out.reason and probe is not None and (pinned or carried(decisive, out.T_a_b, R, p)):
        move = (lambda T: follow(T, pair, p, depth)) if pinned and p.geometric_look else None
        out.reason, moved = moved_by_pull(out.T_a_b, R, probe, p, move)
        if moved is not None:
            return moved
    if not out.reason and p.use_icp:
        out.reason = _colour_gate(best, clouds, p)
    if out.reason:
        return out
    if p.try_mlp and out.inliers >= 30:
        _try_mlp(out, R, inl, clouds[1], p)
    out.merged, out.reason = True, "passed the quality gate"
    return out


def agreeing(T: np.ndarray, R: Correspondences, tol: float) -> np.ndarray:
    """The matches (bool mask) that agree with the chosen alignment T: within `tol` of it,
    or, where more, within `tol` of the least-squares fit of those within 1.5 `tol`. ICP on
    two whole maps that bend settles a few centimetres off where the matched views are
    (HoloLens walk with 1 deg/m of drift: 63 matches within 12 cm, 11 within 8 cm; their own
    fit 8 cm from T). The geometry gate judges T itself."""
    r = residuals(T, R.X, R.Y)
    inl, near = r < tol, r < 1.5 * tol
    if near.sum() < 3:
        return inl
    own = kabsch(R.X[near], R.Y[near])
    inl_own = residuals(own, R.X, R.Y) < tol
    return inl_own if inl_own.sum() > inl.sum() else inl


def _decisive(best, clouds, p: AlignParams) -> bool:
    """`AlignParams.decisive` for the best hypothesis (A's share on B's measured only
    where the rest already holds)."""
    if best.firm_consistency < p.decisive_consistency or best.fitness < 2 * p.min_overlap:
        return False
    v = p.voxel_m
    back = overlap_fitness(
        clouds[0].at(v), clouds[1].at(v, normals=False), invert(best.T_a_b), 2 * v
    )
    return p.decisive(best.firm_consistency, min(best.fitness, back))


def _geometry_gate(best, rivals, p: AlignParams, probe, decisive: bool, noisy) -> str:
    """Why the maps' geometry refuses the best hypothesis, or "" if it does not. A rival is
    far when it moves B's points (`probe`) `rival_m` (RMS) or turns `rival_deg` away.
    Geometry that decides on its own (`decisive`) stands in for the consistency; under the
    bar, the consistency at the robots' depth noise decides: `noisy(T)` says why it fails
    there, or "" (`at_noise` on the pair)."""
    if best.fitness < p.min_overlap:
        return f"the maps overlap on {best.fitness:.2f} of B's cloud (need {p.min_overlap})"
    if best.consistency < p.min_consistency and not decisive:
        why = noisy(best.T_a_b)
        if why:
            return (
                f"free-space consistency {best.consistency:.2f} (need {p.min_consistency}; "
                f"{why}): the aligned maps put surfaces where the cameras saw empty space"
            )
    for h in rivals:
        dt, dr = (
            displacement_rms(h.T_a_b, best.T_a_b, probe),
            transform_error(h.T_a_b, best.T_a_b)[1],
        )
        if (dt > p.rival_m or dr > p.rival_deg) and h.score >= p.ambiguity * best.score:
            return (
                f"ambiguous: a rival alignment {dt:.2f} m / {dr:.0f} deg away scores "
                f"{h.score:.0f} against {best.score:.0f} (self-similar place?)"
            )
    return ""


def at_noise(T: np.ndarray, pair, depth: float, p: AlignParams) -> str:
    """Why T's free space fails at the robots' measured depth noise too, or "": judged with
    every margin no tighter than that noise (the third look's floor, `noise_floor`), its
    consistency as the first look counts it (`consistency_at_noise`) or its firm
    consistency as the third look counts it (`firm_at_floor`) under
    `min_consistency`. A fixed margin (1.5 voxels, 2% of the depth) is tighter than a
    D435's noise from 3 m (3.3 cm RMS a reading): two TUM desk pairs at 1.5 times their
    size scored 0.68-0.69 at it, 0.79 at the noise, firm 0.97 (the truth 0.79, firm 0.99);
    refined, they merge 2.8 and 2.4 cm off at the recording's size (docs/ALIGNER.md,
    session 40). Once per transform (`once` in the pair's memo): `choose` asks it of
    the unrefined winner, the gate of the merge, often the same."""
    return once(pair.memo, "at noise", T, lambda T: _why_at_noise(T, pair, depth, p))


def _why_at_noise(T: np.ndarray, pair, depth: float, p: AlignParams) -> str:
    floor = pair.noise_floor(p.geometric.noise_k)
    if not floor:
        return "no depth noise to judge at"
    c = consistency_at_noise(T, pair.clouds(), *pair.seen(), p, floor)
    firm = firm_at_floor(T, pair, p, depth)
    if min(c, firm) < p.min_consistency:
        return f"{c:.2f}, firm {firm:.2f} at the robots' depth noise"
    return ""


def _colour_gate(best, clouds, p: AlignParams) -> str:
    """Why the grey levels refuse a merge whose free space does not confirm it firmly, or "".

    Under `decisive_consistency` firm, the points where the two maps meet must carry
    grey levels that correlate (Pearson, at the fine voxel) at least
    `min_colour_correlation`. Two different places, the HoloLens lounge and the TUM desk
    both at 0.4 of their size, passed the free-space gate at 0.70 (firm 0.80) with 19
    matches: their grey levels correlate 0.14. A right fit of two HoloLens maps bent by
    1 deg/m of drift has the same free space (0.76, firm 0.81) and 0.46 (0.66 at the
    local truth: a rigid fit of bent maps is off elsewhere); right merges of the kept
    windows at 0.4-2.5 times their scale 0.58-0.94. Colour alone decides nothing: a wrong
    basin of that drifted pair scored 0.58, the first look's winners on pairs of
    different recordings -0.33 to 0.51 (docs/ALIGNER.md)."""
    if best.firm_consistency >= p.decisive_consistency:
        return ""
    v, need = p.voxel_m, p.min_colour_correlation
    r, n = grey_correlation(clouds[0].at(v), clouds[1].at(v, normals=False), best.T_a_b, v)
    if r >= need:  # NaN (under 30 points meet) is not
        return ""
    return (
        f"grey-level correlation {r:.2f} over {n} meeting points (need {need} where the "
        f"firm free-space consistency, {best.firm_consistency:.2f}, is under "
        f"{p.decisive_consistency}): the surfaces that meet do not look alike"
    )


def _match_gate(
    out: AlignResult,
    R: Correspondences,
    inl: np.ndarray,
    p: AlignParams,
    need_spread: float,
    need_inliers: int,
) -> str:
    """Why the inlier matches refuse the fit (count, spread, held-out residual), or ""."""
    if out.inliers < need_inliers:
        return f"{out.inliers} inlier correspondences (need {need_inliers})"
    sp = spread_m(R.X[inl])
    if sp < need_spread:
        return f"inliers spread {sp:.2f} m (need {need_spread:.2f} at this depth)"
    out.holdout_m = holdout_residual(R.X[inl], R.Y[inl])
    if not out.holdout_m <= p.max_holdout_m:
        return f"held-out residual {out.holdout_m:.3f} m (max {p.max_holdout_m:.3f})"
    return ""


def _try_mlp(out: AlignResult, R: Correspondences, inl, cloud_b, p: AlignParams) -> None:
    """The thesis MLP on the inliers, kept where it lowers the rigid fit's held-out error
    by a tenth and stays a correction of it over B's whole map."""
    # at most 1,000 inliers, spread at random: enough for 150 weights, and the
    # cross-validation stays under a second
    idx = np.flatnonzero(inl)
    if len(idx) > 1000:
        idx = np.sort(np.random.default_rng(0).choice(idx, 1000, replace=False))
    rigid_m = holdout_residual(R.X[idx], R.Y[idx])
    # trained only where it could be chosen: where an affine map (closed form, the same
    # folds) already beats the rigid fit by 5%, the maps deform smoothly and a network may
    # take more of it up; where not, the rigid fit explains the matches to their noise (the
    # TUM desk: affine 1.81-1.85 cm against rigid 1.79-1.82 cm, the MLP 1.91-1.93 cm)
    if holdout_residual(R.X[idx], R.Y[idx], model="affine") >= 0.95 * rigid_m:
        return
    out.mlp_holdout_m = holdout_residual(R.X[idx], R.Y[idx], model="mlp")
    if out.mlp_holdout_m < 0.9 * rigid_m:
        mlp = MLPEstimator().fit(R.X[idx], R.Y[idx])
        # a correction, not a reshaping: over B's whole map (beyond the matches, where
        # a network fitted to noise can bend away) it must stay near the rigid fit
        pb = np.asarray(cloud_b.at(p.coarse_voxel_m, normals=False).points)
        bend = float(np.max(np.linalg.norm(mlp.transform(pb) - apply(out.T_a_b, pb), axis=1)))
        if bend <= 2 * p.max_holdout_m:
            out.mlp = mlp
            out.method += "+mlp"
        else:
            log.info("MLP kept out: it bends B's map %.2f m away from the rigid fit", bend)
