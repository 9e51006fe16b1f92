"""Rigid hypotheses for the transform between two maps, and how they are judged and
refined: sequential RANSAC on the pooled matches, one RANSAC per pair, ICP on the clouds,
the free-space test, and the choice among refinements (see `choose`)."""

from __future__ import annotations

import dataclasses
import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from fleetmap.align.types import AlignParams, Hypothesis
from fleetmap.align.validation import outnumbers
from fleetmap.correspondences import Correspondences
from fleetmap.geometry import apply, displacement_rms, invert, residuals, transform_error
from fleetmap.mapcloud import REG, SeenDepth, free_space_check, icp, o3d, overlap_fitness
from fleetmap.registration import ransac_guided, ransac_rigid

log = logging.getLogger(__name__)


def rigid_hypotheses(
    C: Correspondences,
    p: AlignParams,
    min_support: int | None = None,
    guided: bool = False,
    source: str = "pooled",
) -> list[Hypothesis]:
    """Sequential RANSAC: disjoint consensus sets, largest first, each of at least
    `min_support` matches (default: half `p.min_inliers`, and 3). `guided`: samples drawn
    from agreeing matches (`registration.ransac_guided`), else 2,000 uniform ones."""
    X, Y = C.X, C.Y
    floor = max(3, p.min_inliers // 2) if min_support is None else min_support
    left = np.ones(len(X), bool)
    out = []
    for k in range(p.hypotheses):
        if left.sum() < max(p.min_inliers, floor):
            break
        idx = np.flatnonzero(left)
        if guided:
            T, inl = ransac_guided(X[idx], Y[idx], p.ransac_tol_m, seed=k)
        else:
            T, inl = ransac_rigid(X[idx], Y[idx], p.ransac_tol_m, iterations=2000, seed=k)
        if inl.sum() < floor:
            break
        out.append(Hypothesis(T, int(inl.sum()), source))
        left[idx[inl]] = False
    return out


def raw_hypotheses(R: Correspondences, p: AlignParams) -> list[Hypothesis]:
    """Sequential RANSAC over every view pair's raw matches pooled, for a consensus spread
    over many view pairs with a few matches each, which no pair's own RANSAC sees: SUN3D
    windows sharing 35% of their maps, with ASIFT's matches, hold 81-143 matches within 5 cm
    of the truth over 24-36 view pairs (2-12 each), 2-3.5% of 4,000-5,000 (hence guided
    samples). Kept where a consensus is at least twice what chance gives: the largest
    consensus of the same matches shuffled (B's points against other A points), which
    follows the number of matches and the scene's extent.

    Opt-in (`AlignParams.raw_consensus`), measured in session 13: it found the right
    consensus for the SUN3D misses, where the gate then refused them still (a look-alike
    rival at 0.93 of the score; matches agreeing better 0.26 m away), and on robot A's last
    keyframes against robot B it proposed a basin the colour ICP slid 12.6 cm / 3.1 deg
    from the truth that the gate passed (matches agree with it as with the truth, 148 and
    157): a wrong merge where the default refuses. docs/ALIGNER.md."""
    if len(R) < p.min_inliers:
        return []
    Y = R.Y[np.random.default_rng(0).permutation(len(R))]
    _, inl = ransac_guided(R.X, Y, p.ransac_tol_m)
    floor = max(p.min_inliers, 2 * int(inl.sum()))
    return rigid_hypotheses(R, p, floor, guided=True, source="raw pooled")


def pair_hypotheses(R: Correspondences, p: AlignParams) -> list[Hypothesis]:
    """One rigid RANSAC per pair on its raw matches: a wide-baseline pair may hold only a
    handful of right matches, drowned when pooled with a look-alike place's many."""
    out = []
    for k in np.unique(R.pair):
        m = R.pair == k
        if m.sum() < p.pair_min_support + 1:
            continue
        T, inl = ransac_rigid(R.X[m], R.Y[m], 1.25 * p.ransac_tol_m, iterations=200, seed=int(k))
        if inl.sum() >= p.pair_min_support:
            out.append(Hypothesis(T, int(inl.sum()), f"pair {int(k)}"))
    return out


def probe_points(cloud) -> np.ndarray:
    """About 300 of a cloud's points, (N, 3): what moving a map means, measured."""
    pts = np.asarray(cloud.points)
    return pts[:: max(1, len(pts) // 300)]


def beyond_rivals(T: np.ndarray, T0: np.ndarray, probe: np.ndarray, p: AlignParams) -> str:
    """How far T lies from T0 ("0.80 m / 14 deg") where that is beyond the gate's rivals
    (`rival_m`, `rival_deg`), else "": a passing rival, or a refinement that slid. A
    HoloLens lounge window merged with a SUN3D study room (other map frames) on a basin at
    overlap 0.11 whose refinement slid 0.79 m / 14 deg; right merges' refinements moved
    0-1 cm (docs/ALIGNER.md, session 27)."""
    dt, dr = displacement_rms(T, T0, probe), transform_error(T, T0)[1]
    return f"{dt:.2f} m / {dr:.0f} deg" if dt > p.rival_m or dr > p.rival_deg else ""


def _distinct(hyps: list[Hypothesis], probe: np.ndarray, min_m: float) -> list[Hypothesis]:
    """Greedy: keep a hypothesis unless it moves the probe points within `min_m` (RMS) of
    one already kept. Order = priority."""
    kept: list[Hypothesis] = []
    moved: list[np.ndarray] = []
    for h in hyps:
        q = apply(h.T_a_b, probe)
        if all(np.sqrt(((q - r) ** 2).sum(1).mean()) > min_m for r in moved):
            kept.append(h)
            moved.append(q)
    return kept


def _judge(h: Hypothesis, cloud_b, cloud_a, views_a, views_b, margin: float, fit_d: float):
    pb, pa = np.asarray(cloud_b.points), np.asarray(cloud_a.points)
    s1, c1, f1 = free_space_check(apply(h.T_a_b, pb), views_a, margin)
    s2, c2, f2 = free_space_check(apply(invert(h.T_a_b), pa), views_b, margin)
    h.supports, h.conflicts, h.firm_conflicts = s1 + s2, c1 + c2, f1 + f2
    h.fitness = overlap_fitness(cloud_b, cloud_a, h.T_a_b, fit_d)


def consistency_at_noise(T: np.ndarray, clouds, views_a, views_b, p: AlignParams, floor) -> float:
    """T's free-space consistency as `choose` judges it on the fine clouds (margin 1.5
    voxels and 2% of the depth), with tol no tighter than `floor(depth)`: the spread
    between the two robots' readings at that depth (`_PairClouds.noise_floor`, the third
    look's). Under the fixed margin a D435 seen from 3 m (3.3 cm RMS a reading) puts right
    surfaces in each other's seen-empty space: two TUM desk pairs at 1.5 times their size
    scored 0.69 and 0.68 (need 0.7), 0.79 at the noise; merged, 2.8 and 2.4 cm from the
    truth (docs/ALIGNER.md, session 40)."""
    v1 = p.voxel_m
    pb, pa = np.asarray(clouds[1].at(v1, normals=False).points), np.asarray(clouds[0].at(v1).points)
    s1, c1, _ = free_space_check(apply(T, pb), _seen(views_a), 1.5 * v1, floor=floor)
    s2, c2, _ = free_space_check(apply(invert(T), pa), _seen(views_b), 1.5 * v1, floor=floor)
    return (s1 + s2) / max(s1 + s2 + c1 + c2, 1)


def _visual_cost(T: np.ndarray, R: Correspondences, tol: float) -> tuple[float, int]:
    """Truncated mean residual of the raw matches under T, and how many are within tol."""
    if not len(R):
        return tol, 0
    r = residuals(T, R.X, R.Y)
    return float(np.minimum(r, tol).mean()), int(np.count_nonzero(r < tol))


def choose(
    hyps, R: Correspondences, views_a, views_b, clouds, p: AlignParams, memo=None, noisy=None
):
    """Coarse: point-to-plane ICP of every distinct hypothesis on coarse clouds, judged by
    the free-space test; those that keep visual support (at least `min_inliers` raw
    matches agreeing) are judged again on the fine clouds, the best few; the winner is
    refined two ways (fine point-to-plane ICP, multi-scale coloured ICP) and the refinement
    the raw matches agree with best is kept. Returns (best, distinct rivals judged the same
    way). `noisy`: the gate's judging at the robots' depth noise (`refused_whatever_refined`).

    Why two refinements: in a room of floor, walls and desks, fine point-to-plane ICP
    slides along the planes (SUN3D: 8-12 cm from the ground truth, started at the ground
    truth itself) where colour texture pins the slide (2-3 cm); on exact simulated data the
    plain point-to-plane fit is the better one (0.08 against 0.2-2 cm), and where colour is
    not registered to depth, colour pulls the fit off (HoloLens lounge: 1.6 cm coloured, 1.0
    cm geometric). The matches decide where they can tell (`ranked`: agreeing within 4 cm,
    beyond the counts' noise), the depth where they cannot: on 17 recall pairs the depth
    alone chose the worse refinement 6 times (up to 7.0 against 2.7 cm), this rule once
    (a tie, 3.3 against 0.4 cm). See docs/ALIGNER.md. `views_a`, `views_b`: RGB-D views or
    their `SeenDepth` (the third look's, whose nearest-reading images are then made once).
    `memo` (a dict, or None): ICPs, judgements and refinements by the transform they started
    from, for a second call on the same clouds and views (the second look's)."""
    v0, v1 = p.coarse_voxel_m, p.voxel_m
    views_a, views_b = _seen(views_a), _seen(views_b)
    ca0, cb0 = clouds[0].at(v0), clouds[1].at(v0, normals=False)  # B's: ICP's source
    probe = probe_points(cb0)
    hyps = _distinct(sorted(hyps, key=lambda h: -h.support), probe, p.dedupe_m)
    hyps = hyps[: p.max_candidates]
    log.debug("%d distinct hypotheses", len(hyps))
    memo = {} if memo is None else memo
    for h in hyps:
        h.T_a_b = once(memo, "icp", h.T_a_b, lambda T: icp(cb0, ca0, T, (4 * v0, 1.5 * v0), 15)[0])
    hyps = _distinct(hyps, probe, v0)
    for h in hyps:
        h.support = _visual_cost(h.T_a_b, R, 1.5 * p.ransac_tol_m)[1]
    backed = [h for h in hyps if h.support >= p.min_inliers] or hyps
    # the others are not looked at again: not judged either
    _judged(memo, "coarse", backed, cb0, ca0, views_a, views_b, 1.25 * v0, 1.25 * v0)
    backed.sort(key=lambda h: -h.score)
    top = backed[: p.refine]
    ca1, cb1 = clouds[0].at(v1), clouds[1].at(v1, normals=False)
    _judged(memo, "fine", top, cb1, ca1, views_a, views_b, 1.5 * v1, 2 * v1)
    top.sort(key=lambda h: -h.score)
    best = top[0]
    if refused_whatever_refined(best, p, noisy):
        return best, top[1:]
    refined = once(memo, "refine", best.T_a_b, lambda T: _refinements(T, clouds, p))
    refined = [(T, best.source + how) for T, how in refined]
    for T, source in ranked(refined, R, cb1, ca1, p):
        dt, dr = displacement_rms(T, best.T_a_b, probe), transform_error(T, best.T_a_b)[1]
        kept = _visual_cost(T, R, 1.5 * p.ransac_tol_m)[1]
        # a refinement, not a jump elsewhere, and one the matches that proposed it still
        # back (coloured ICP on bent maps slid 0.22 m off every match: docs/ALIGNER.md)
        if dt <= p.rival_m and dr <= p.rival_deg and 2 * kept >= best.support:
            # rivals were judged unrefined: compare like with like (the same counts)
            polished = dataclasses.replace(best, T_a_b=T, source=source)
            polished.fitness = overlap_fitness(cb1, ca1, T, 2 * v1)
            return polished, _rivals(polished, top[1:], R, clouds, (cb1, ca1), probe, p, memo)
    return best, _rivals(best, top[1:], R, clouds, (cb1, ca1), probe, p, memo)


def _rivals(best, others, R: Correspondences, clouds, fine, probe, p: AlignParams, memo) -> list:
    """`others` but those that refine into `best`'s place: a rival scoring near the best
    (`ambiguity`) beyond the rivals' distance is refined as the winner was (`_refinements`,
    the one the raw matches agree with best), and where it lands within the rivals'
    distance of the winner the two were one basin the coarse ICP left apart, not two
    places. Others are kept as they are (judged unrefined, as the winner's counts).
    `fine`: B's and A's clouds at the fine voxel."""
    kept = []
    for h in others:
        if beyond_rivals(h.T_a_b, best.T_a_b, probe, p) and h.score >= p.ambiguity * best.score:
            refined = once(memo, "refine", h.T_a_b, lambda T: _refinements(T, clouds, p))
            T = ranked([(T, h.source + how) for T, how in refined], R, *fine, p)[0][0]
            if not beyond_rivals(T, best.T_a_b, probe, p):
                log.info("a rival refined into the winner's place: one basin")
                continue
        kept.append(h)
    return kept


def _seen(views) -> list[SeenDepth]:
    """Views as `SeenDepth`, those already so kept (with their nearest-reading images)."""
    return [v if isinstance(v, SeenDepth) else SeenDepth(v) for v in views]


def refused_whatever_refined(best: Hypothesis, p: AlignParams, noisy=None) -> bool:
    """Whether the geometry gate refuses `best` however it is refined: its free-space
    consistency under `min_consistency` and its firm consistency under
    `decisive_consistency` (so the maps' geometry cannot decide on its own), and, given
    `noisy` (T -> why T's free space fails at the robots' depth noise, or "":
    `pipeline.at_noise`), failing there too (judged unrefined, as the counts). A refinement
    keeps the hypothesis's free-space counts (`choose`: rivals were judged unrefined), so
    neither can change, and `pipeline._geometry_gate` refuses on the overlap or the
    consistency. Refining such a winner was 60-70 % of `choose` on refused pairs (two
    HoloLens robots against one from another building: coloured ICP sliding 0.4-1.7 m on
    clouds of 70-110k points, 6-8 s of 9-12 s) for nothing."""
    if best.consistency >= p.min_consistency or best.firm_consistency >= p.decisive_consistency:
        return False
    return noisy is None or bool(noisy(best.T_a_b))


def ranked(cands: list[tuple[np.ndarray, str]], R: Correspondences, cb1, ca1, p: AlignParams):
    """The refinements [(T_a_b, source)], best first: by how many raw matches agree within
    half the RANSAC tolerance; those whose count is within the noise of a difference of two
    counts (the square root of their sum) of the most are tied, and their surfaces decide
    (`surface_rmse`, depth only)."""
    half = [int(np.count_nonzero(residuals(T, R.X, R.Y) < p.ransac_tol_m / 2))
            for T, _ in cands]  # fmt: skip
    top = max(half)
    tied = [k for k, n in enumerate(half) if not outnumbers(top, n)]
    rest = sorted((k for k in range(len(cands)) if k not in tied), key=lambda k: -half[k])
    tied.sort(key=lambda k: surface_rmse(cb1, ca1, cands[k][0], p.voxel_m))
    return [cands[k] for k in tied + rest]


def once(memo: dict, kind: str, T: np.ndarray, make):
    """memo[(kind, T)], made by make(T) the first time: make runs once per transform."""
    key = (kind, np.asarray(T, np.float64).tobytes())
    if key not in memo:
        memo[key] = make(T)
    return memo[key]


def _judged(memo: dict, kind: str, hyps: list[Hypothesis], *args) -> None:
    """`_judge` of each hypothesis, or its counts and fitness from `memo` for the same
    transform. Two threads, one hypothesis each (distinct transforms: `memo`'s keys never
    collide; a view's nearest-reading image may be made twice, the same both times):
    numpy's work on the projected points releases the GIL (SUN3D's ten judgements 0.93 ->
    0.63 s, the same counts; no gain on a desk's smaller clouds; docs/BENCHMARKS.md,
    session 42)."""

    def judged(h: Hypothesis) -> None:
        def judge(T):
            _judge(h, *args)
            return h.supports, h.conflicts, h.firm_conflicts, h.fitness

        h.supports, h.conflicts, h.firm_conflicts, h.fitness = once(memo, kind, h.T_a_b, judge)

    with ThreadPoolExecutor(2) as ex:
        list(ex.map(judged, hyps))


def _refinements(T0: np.ndarray, clouds, p: AlignParams) -> list[tuple[np.ndarray, str]]:
    """The best hypothesis refined two ways: point-to-plane ICP (the wide distances on the
    coarser colour scale's cloud, the last on the fine one), and multi-scale coloured ICP
    where both clouds have colour, from T0. Returns [(T_a_b, "+icp" or "+colour")]."""
    v1 = p.voxel_m
    ca1, cb1 = clouds[0].at(v1), clouds[1].at(v1, normals=False)
    refined = [(depth_refinement(T0, clouds, p), "+icp")]
    if not (p.colour_icp and ca1.has_colors() and cb1.has_colors()):
        return refined
    T = colour_icp(T0, clouds, (4 * v1 / 3, 2 * v1 / 3), 20, p.match_exposure)
    return refined if T is None else [*refined, (T, "+colour")]


def depth_refinement(T0: np.ndarray, clouds, p: AlignParams) -> np.ndarray:
    """T0 (T_a_b) refined by point-to-plane ICP of B's cloud onto A's: the wide distances
    on the coarser colour scale's cloud (4/3 of the gate's voxel), the last on the gate's."""
    v1 = p.voxel_m
    vm = 4 * v1 / 3
    T, _, _ = icp(clouds[1].at(vm, normals=False), clouds[0].at(vm), T0, (3 * v1, 1.5 * v1), 20)
    return icp(clouds[1].at(v1, normals=False), clouds[0].at(v1), T, (v1,), 20)[0]


def colour_icp(
    T: np.ndarray, clouds, scales, iterations: int, match_exposure: bool = False
) -> np.ndarray | None:
    """T_a_b refined by Open3D's coloured ICP of B's cloud onto A's at each voxel of
    `scales` in turn (within 1.5 voxels), B's grey levels matched to A's where they meet
    if `match_exposure` (`exposure_matched`), or None where the clouds lack colour or too
    few points have colour gradients."""
    for v in scales:
        ca, cb = clouds[0].at(v), clouds[1].at(v, normals=False)
        if not (ca.has_colors() and cb.has_colors()):
            return None
        try:
            r = REG.registration_colored_icp(
                exposure_matched(cb, ca, T, 1.5 * v) if match_exposure else cb,
                ca,
                1.5 * v,
                T,
                REG.TransformationEstimationForColoredICP(),
                REG.ICPConvergenceCriteria(max_iteration=iterations),
            )
        except RuntimeError:  # too few points with colour gradients
            return None
        T = np.asarray(r.transformation)
    return T


#: Point pairs `exposure_matched` needs to match two maps' grey levels: ten a quantile bin.
EXPOSURE_PAIRS = 10 * 20


def exposure_matched(source, target, T: np.ndarray, distance: float):
    """`source` (an Open3D cloud with colours) in grey levels matched to `target`'s where
    the two meet: the source points within `distance` of the target under T and the target
    points they meet, each set's grey levels (the mean of red, green and blue, as coloured
    ICP reads them) at every 5% quantile, and each source level carried to the target's
    level at its quantile (histogram specification; levels between quantiles linearly).
    Coloured ICP takes a difference of brightness for a displacement: robots whose cameras
    expose differently (auto-exposure settled facing a window or a dark corner, another
    make's gamma and white balance) moved five real pairs' refinements 10-31 mm, the desk's
    0.2-1.8 mm once matched (docs/ALIGNER.md, session 61). Only where the difference is
    the cameras': where the mapping explains less of the pairs' grey difference than it
    leaves (median |A - B| over sqrt(2) or more after it: a global mapping and the pairs'
    own scatter add in quadrature), the levels differ by what each robot saw of the overlap
    (highlights, viewpoints; the HoloLens walk's ratio 0.8-1.0 at one exposure, B exposed
    x0.6 or x1.3 0.19-0.59) and matching them moved two right merges 2-3 cm (session 62):
    `source` itself then, as where fewer than `EXPOSURE_PAIRS` points meet; otherwise a
    copy, grey."""
    pairs = np.asarray(REG.evaluate_registration(source, target, distance, T).correspondence_set)
    if len(pairs) < EXPOSURE_PAIRS:
        return source
    grey_s = np.asarray(source.colors).mean(1)
    grey_t = np.asarray(target.colors).mean(1)
    q = np.linspace(0, 1, 21)
    gs, gt = grey_s[pairs[:, 0]], grey_t[pairs[:, 1]]
    xs, xt = np.quantile(gs, q), np.quantile(gt, q)
    # a level held by several quantiles (a clipped highlight, a crushed shadow) is carried
    # to the mean of the target's levels at them
    xs, tie = np.unique(xs, return_inverse=True)
    xt = np.bincount(tie, xt) / np.bincount(tie)

    def mapped(g):
        return np.interp(g, xs, xt) if len(xs) > 1 else np.full_like(g, xt[0])

    if np.median(np.abs(gt - mapped(gs))) * np.sqrt(2) >= np.median(np.abs(gt - gs)):
        return source
    grey = mapped(grey_s)
    out = o3d.geometry.PointCloud(source)
    out.colors = o3d.utility.Vector3dVector(np.repeat(grey[:, None], 3, axis=1))
    return out


def surface_rmse(source, target, T: np.ndarray, distance: float) -> float:
    """RMS distance (metres) of the source points that land within `distance` of the
    target under T, a tenth more for every tenth of the source that does not: how closely
    two maps' surfaces sit, measured on depth alone."""
    ev = REG.evaluate_registration(source, target, distance, T)
    if ev.fitness == 0:
        return float("inf")
    return float(ev.inlier_rmse) * (1.0 + (1.0 - ev.fitness))
