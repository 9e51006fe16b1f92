"""A third look at a pair both image looks refused: the maps' geometry proposes, their free
space and their colour decide.

Where two robots saw the same surfaces from directions far apart, no image matcher ties
their views (HoloLens walk, 27% of the maps shared: 6 of 1,110 raw matches agree with the
truth, ASIFT included). The fused depth of the views sent still holds the shared surfaces.
FPFH features on it and feature RANSAC (Open3D, the map_merge_3d recipe's registration)
propose alignments, and so do the rotations between the two maps' dominant planes
(`fleetmap.align.manhattan`, where FPFH's histograms of two partial views differ); each
start refined by point-to-plane ICP lands in one of a few basins, the right one among them
often enough (docs/ALIGNER.md, "A third look: the maps' geometry, judged by free space and
colour", and its session 16 part).

Geometry alone does not decide: on rooms of floor and walls a wrong basin may put no point
in space the other robot saw empty (cross-recording pairs up to 1.00 both ways), and a
right one with a slide along a bookshelf scores nearly as well as the truth. What tells
them apart is what the surfaces look like: the points of both maps that meet should carry
the same grey levels up to gain and offset (Pearson correlation; right alignments of the
recall bench 0.56-0.92, wrong ones with the free space clean -0.38 or less), while the free
space, judged tightly, refuses slides (wrong ones with a correlation of 0.5 or more: firm
consistency 0.82 or less). A merge needs both, both ways, on the gate's overlap, with
relief where the maps meet (`surfaces.relief`: on one plane the free space cannot tell
where along it, and grey levels alone decide), and no other basin that passes as far away
as the gate's rivals (`rival_m`, `rival_deg`). Every length follows the scene's median
depth, and the free space is judged no tighter than the depth noise the two robots' own
views show at each depth (`GeometricLook.noise_k`, `fleetmap.depth_noise`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from fleetmap.align.hypotheses import (
    beyond_rivals,
    colour_icp,
    depth_refinement,
    probe_points,
)
from fleetmap.align.manhattan import manhattan_starts
from fleetmap.align.surfaces import grey_correlation, relief
from fleetmap.align.types import AlignParams, AlignResult, GeometricLook
from fleetmap.geometry import apply, displacement_rms, invert
from fleetmap.mapcloud import REG, SEEDED, free_space_check, icp, overlap_fitness

log = logging.getLogger(__name__)


#: fewer points than this in either map at the FPFH voxel: no look (RANSAC's samples and
#: the correlation need a few hundred)
MIN_POINTS = 200

#: a basin whose grey levels correlate less than `min_correlation` minus this at the FPFH
#: voxel is neither refined at half a voxel nor judged (half of them: the refinement and
#: judging were a third of the look). Over 2,250 basins of the kept recall windows and
#: pairs of different recordings, refining raised the correlation by 0.42 at most (99%
#: within 0.18), and none of those under 0.1 before reached 0.26 after
COARSE_SLACK = 0.45

#: a basin whose firm free-space consistency (`firm_ways`, as judged) is under the look's
#: bar minus this before refining is not refined nor judged: refining at half a voxel
#: raised it by 0.068 at most over 198 basins of 13 pairs through a D435's noise, 0.083
#: over 109 of 8 others (docs/ALIGNER.md, session 39), and 58-69% of the basins sit that
#: low; refining and judging them was a quarter of a refused HoloLens pair's alignment
FIRM_SLACK = 0.2


@dataclass
class Judged:
    """One refined basin: T_a_b, each map's share on the other (within half a voxel),
    firm free-space consistency each way, the grey-level correlation and its point count,
    the relief of the surfaces that meet (`surfaces.relief`) at the look's voxel `voxel_m`,
    and how many seeds landed here."""

    T_a_b: np.ndarray
    overlap: tuple[float, float]
    firm: tuple[float, float]
    correlation: float
    meeting: int
    relief_m: float = float("inf")
    voxel_m: float = 0.0
    seeds: int = 1

    @property
    def score(self) -> float:
        """The smaller way's firm consistency plus the correlation: which basin passes best."""
        return min(self.firm) + self.correlation

    def passes(self, look: GeometricLook, p: AlignParams) -> bool:
        return (
            min(self.overlap) >= p.min_overlap
            and min(self.firm) >= look.min_consistency
            and self.correlation >= look.min_correlation
            and self.relief_m >= self.voxel_m
        )

    def why_not(self, look: GeometricLook, p: AlignParams) -> str:
        return (
            f"overlap {min(self.overlap):.2f} (need {p.min_overlap}), firm free-space "
            f"consistency {min(self.firm):.2f} (need {look.min_consistency}), grey-level "
            f"correlation {self.correlation:.2f} (need {look.min_correlation}), relief where "
            f"the maps meet {self.relief_m:.2f} m (need the look's voxel, {self.voxel_m:.2f} m)"
        )


def basins(
    clouds, voxel: float, look: GeometricLook, min_fitness: float = 0.0
) -> list[tuple[np.ndarray, int]]:
    """FPFH + feature RANSAC seeds on the clouds at `voxel`, and `look.plane_starts` from
    the rotations between the maps' dominant planes (`manhattan.manhattan_starts`, kept
    where their ICP overlaps at least `min_fitness` of B), each refined by point-to-plane ICP
    there; basins closer than a voxel (RMS over B's points) merged (`refine` takes one to
    half a voxel). Returns [(T_a_b, starts that landed there)], most starts first."""
    import open3d as o3d

    ca, cb = clouds[0].at(voxel), clouds[1].at(voxel)
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    fa, fb = REG.compute_fpfh_feature(ca, param), REG.compute_fpfh_feature(cb, param)
    # the feature matches once each way (plain, mutual), not once a seed: Open3D's
    # feature RANSAC makes the same ones on every call (`correspondences_from_features`)
    # (where few survive the mutual filter Open3D takes the plain ones, and says so on
    # stderr past the CLI's -q: not a warning for the user)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        matched = {m: REG.correspondences_from_features(fb, fa, m) for m in (False, True)}
    probe = probe_points(cb)
    found: list[list] = []
    for seed in range(look.seeds):
        with SEEDED:
            o3d.utility.random.seed(seed)
            r = REG.registration_ransac_based_on_correspondence(
                cb, ca, matched[seed % 2 == 1], 1.5 * voxel,
                REG.TransformationEstimationPointToPoint(False), 3,
                [REG.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 REG.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                REG.RANSACConvergenceCriteria(look.iterations, 0.999),
            )  # fmt: skip
        _land(found, icp(cb, ca, r.transformation, (2 * voxel, voxel), 30)[0], probe, voxel)
    for T0 in manhattan_starts(ca, cb, voxel, look.plane_starts):
        T, fit, _ = icp(cb, ca, T0, (2 * voxel, voxel), 30)
        if fit >= min_fitness:
            _land(found, T, probe, voxel)
    found.sort(key=lambda b: -b[1])
    return [(T, n) for T, n in found]


def refine(T: np.ndarray, clouds, voxel: float) -> np.ndarray:
    """A basin's T_a_b refined by point-to-plane ICP at half a voxel."""
    b = clouds[1].at(voxel / 2, normals=False)  # ICP's source: B's normals are not read
    return icp(b, clouds[0].at(voxel / 2), T, (voxel / 2,), 30)[0]


def _land(found: list[list], T: np.ndarray, probe: np.ndarray, voxel: float) -> None:
    """Count T in the basin (`found`: [T, starts]) within a voxel of it, or open one."""
    for b in found:
        if displacement_rms(b[0], T, probe) < voxel:
            b[1] += 1
            return
    found.append([T, 1])


def judge(T: np.ndarray, clouds, seen, voxel: float, floor=None) -> Judged:
    """Overlap, firm free-space consistency (at half a voxel, of the points off depth
    edges: `ViewsCloud.off_edges`; no tighter than `floor` of the depth read, the depth's
    noise: `_PairClouds.noise_floor`), grey-level correlation and the relief where the maps
    meet (`surfaces.relief`) of an alignment, both ways.
    `seen`: each robot's views as `SeenDepth`."""
    half = voxel / 2
    ca, cb = clouds[0].at(half), clouds[1].at(half, normals=False)  # B's: points, colours
    r, n = grey_correlation(ca, cb, T, half)
    return Judged(
        T,
        (overlap_fitness(cb, ca, T, half), overlap_fitness(ca, cb, invert(T), half)),
        firm_ways(T, clouds, seen, voxel, floor),
        r if np.isfinite(r) else -1.0,
        n,
        relief(ca, cb, T, half),
        voxel,
    )


def firm_ways(T: np.ndarray, clouds, seen, voxel: float, floor=None) -> tuple[float, float]:
    """T's firm free-space consistency each way (B's points in A's views, A's in B's), as
    `judge` counts it: the points off depth edges, at half a voxel or `floor`."""
    pa, pb = (c.off_edges(2 * voxel) for c in clouds)
    s_b, _, f_b = free_space_check(apply(T, pb), seen[0], voxel / 2, 0.0, floor)
    s_a, _, f_a = free_space_check(apply(invert(T), pa), seen[1], voxel / 2, 0.0, floor)
    return s_b / max(s_b + f_b, 1), s_a / max(s_a + f_a, 1)


def look_voxel(p: AlignParams, depth: float) -> float:
    """The look's FPFH voxel: `voxel_rel` of the views' median depth, one to five of the
    gate's voxels."""
    return float(np.clip(p.geometric.voxel_rel * depth, p.voxel_m, 5 * p.voxel_m))


def firm_at_noise(T: np.ndarray, pair, p: AlignParams, depth: float) -> float:
    """T's firm free-space consistency at this look's voxel (`firm_ways`, as `judge` counts
    it, at half of it: 2.5% of the scene's depth), the smaller way: without the look's noise
    floor, the margin `unfirm` and `pulls.falls_back` were measured at (docs/ALIGNER.md, session
    38)."""
    return min(firm_ways(T, pair.clouds(), pair.seen(), look_voxel(p, depth)))


def firm_at_floor(T: np.ndarray, pair, p: AlignParams, depth: float) -> float:
    """`firm_at_noise` with the look's own margin: no tighter than its noise floor
    (`_PairClouds.noise_floor`), as `judge` counts it."""
    floor = pair.noise_floor(p.geometric.noise_k)
    return min(firm_ways(T, pair.clouds(), pair.seen(), look_voxel(p, depth), floor))


def blurred(blur: float, voxel: float, depth: float) -> str:
    """Why this look does not judge where the free-space margin at the scene's depth (the
    noise floor, `blur`, metres) is wider than its voxel: there the free space cannot tell
    alignments a voxel apart, and the look would rest on grey levels alone. Recall seed 53
    (the rooms at twice their size through a D435's noise: the readings of the two robots
    spread 11.7 cm at the HoloLens windows' median depth of 4.8 m, a floor of 23 cm over a
    15 cm voxel) merged a HoloLens pair 24 cm off (at the recording's size) at firm 0.98,
    correlation 0.52, the truth firm 0.99; in that draw and seed 51's (1.5 times, floors
    6-12 cm under 7.5-15 cm voxels) the look merged nothing else (docs/ALIGNER.md, session
    40)."""
    return (
        f"at the scene's depth ({depth:.1f} m) the robots' depth noise widens the free-space "
        f"margin to {blur:.2f} m, beyond this look's {voxel:.2f} m voxel: its free space "
        "cannot tell alignments a voxel apart"
    )


def geometric_look(pair, p: AlignParams, depth: float) -> AlignResult:
    """Align the pair's views on their fused depth alone (`basins`), judged by `judge`, with
    `p.geometric`'s settings. `pair`: the pipeline's `_PairClouds`."""
    look, voxel = p.geometric, look_voxel(p, depth)
    clouds = pair.clouds()
    few = min(len(c.at(voxel).points) for c in clouds)
    if few < MIN_POINTS:
        return AlignResult(False, f"{few} points at a {voxel:.2f} m voxel (need {MIN_POINTS})")
    seen, floor = pair.seen(), pair.noise_floor(look.noise_k)  # `seen`: for `choose` too
    blur = float(floor(np.array([depth]))[0]) if floor else 0.0
    if blur > voxel:
        return AlignResult(False, blurred(blur, voxel, depth))
    found = basins(clouds, voxel, look, p.min_overlap)
    judged, why = judged_basins(found, clouds, seen, voxel, look, floor)
    if why:
        return AlignResult(False, f"no alignment passes: {why}")
    passing = sorted((j for j in judged if j.passes(look, p)), key=lambda j: -j.score)
    log.info("geometric look: %d basins, %d judged, %d pass", len(found), len(judged), len(passing))
    if not passing:
        best = max(judged, key=lambda j: j.score)
        return AlignResult(False, f"no alignment passes: at best {best.why_not(look, p)}")
    win, probe = passing[0], probe_points(clouds[1].at(voxel))
    for j in passing[1:]:  # basins a voxel apart may refine into one place: rivals are far
        far = beyond_rivals(j.T_a_b, win.T_a_b, probe, p)
        if far:
            return AlignResult(False, f"ambiguous: another alignment {far} away passes too")
    return settle(win, pair, p, voxel, floor, f"{len(found)} basins ({win.seeds} seeds)")


def settle(win: Judged, pair, p: AlignParams, voxel: float, floor, found: str) -> AlignResult:
    """The look's merge at a basin that passed (`win`): refined on depth alone as the first
    look refines its winner (`hypotheses.depth_refinement`), kept unrefined where the
    refinement slides off what passed, refused where it slides as far as a rival. `found`:
    how the basin was found, for the reason. This look's evidence is the maps' depth, and
    few raw matches are left to choose between refinements (docs/ALIGNER.md, session 54):
    - not by coloured ICP: of the 13 merges of five recall draws, the 4 refined by colour
      (HoloLens through a D435's noise) stood 5.6-10.6 cm off, point-to-plane from the
      same basins 3.2-6.5;
    - not from `choose`'s coarse ICP, whose reach (4 coarse voxels) is wider than the ICP
      that settled the basin: it slid a passing basin 7.8 cm from the truth to 29 cm, and
      the pair was refused (recall seed 83, 18% shared; 6.0 cm without it)."""
    look, clouds, seen = p.geometric, pair.clouds(), pair.seen()
    probe = probe_points(clouds[1].at(voxel))
    T = depth_refinement(win.T_a_b, clouds, p)
    refined, method = judge(T, clouds, seen, voxel, floor), "fpfh+icp+icp"
    if not refined.passes(look, p):  # the refinement slid off what passed: keep the basin,
        slid = beyond_rivals(T, win.T_a_b, probe, p)
        if slid:  # unless it slid as far as a rival: no basin holds there
            return AlignResult(
                False, f"the best alignment does not hold: refined, it slid {slid} to "
                f"where the gate refuses it ({refined.why_not(look, p)})",
            )  # fmt: skip
        refined, method = win, "fpfh+icp"
    return merged(refined, method, found)


def merged(j: Judged, method: str, found: str) -> AlignResult:
    """The look's merge at `j`, with why it passed. `found`: how it was found."""
    return AlignResult(
        True,
        "passed on the maps' geometry and colour: firm free-space consistency "
        f"{min(j.firm):.2f}, grey-level correlation {j.correlation:.2f} over {j.meeting} "
        f"points, overlap {min(j.overlap):.2f}, {found}",
        j.T_a_b,
        method,
        fitness=j.overlap[0],
    )


def judged_basins(found, clouds, seen, voxel: float, look: GeometricLook, floor):
    """The basins (`basins`) worth refining, refined (`refine`) and judged (`judge`): those
    whose grey levels correlate at least `min_correlation` - `COARSE_SLACK` and whose firm
    free space holds at least `min_consistency` - `FIRM_SLACK` before refining. Returns
    ([Judged], "") or ([], why none was judged)."""
    ca, cb = clouds[0].at(voxel), clouds[1].at(voxel)
    screen, firm_bar = look.min_correlation - COARSE_SLACK, look.min_consistency - FIRM_SLACK
    coarse = [grey_correlation(ca, cb, T, voxel)[0] for T, _ in found]
    judged, firms = [], []
    for (T, n), r in zip(found, coarse, strict=True):
        if not r >= screen:  # NaN (under 30 points meet) is not
            continue
        firms.append(min(firm_ways(T, clouds, seen, voxel, floor)))
        if firms[-1] >= firm_bar:  # refined on depth, and on colour too (a voxel, half)
            colour = colour_icp(T, clouds, (voxel, voxel / 2), 30) if look.colour_refine else None
            for Tr in (refine(T, clouds, voxel), colour):
                if Tr is not None:
                    judged.append(judge(Tr, clouds, seen, voxel, floor))
                    judged[-1].seeds = n
    if judged:
        return judged, ""
    if firms:
        return [], (
            f"firm free-space consistency at best {max(firms):.2f} before refining (judged "
            f"from {firm_bar:.2f}, need {look.min_consistency})"
        )
    r = max((x for x in coarse if np.isfinite(x)), default=float("nan"))
    return [], (
        f"grey-level correlation at best {r:.2f} before refining (judged from {screen:.2f}, "
        f"need {look.min_correlation})"
    )


def unfirm(T: np.ndarray, pair, p: AlignParams, depth: float) -> str:
    """Why a second look's merge T does not hold its free space judged as this look judges
    (`judge` at its voxel: a sensor's noise at the scene's depth), or "": firm under even
    the first look's bar (`min_consistency`, 0.7) either way.

    The second look merges on raw ASIFT matches that the first look's free-space test, at
    its wider margin, confirms. A HoloLens pair (21% shared) at 0.6 of its size, through a
    D435's noise and with B as a 16:9 camera, was merged 41-45 cm off in five of six pairs
    of map frames: 16 matches agreeing, free space 0.72 at the first look's margin, firm
    0.59-0.61 here (the truth 0.99). The right second-look merges of three draws (HoloLens,
    SUN3D, a desk's scale, a D435's noise, another camera) are firm 0.91-0.98 here, the
    loose SUN3D one (9.9 cm, its truth good to 1.5 deg) 0.88 (docs/ALIGNER.md, session 35)."""
    firm = firm_at_noise(T, pair, p, depth)
    if firm >= p.min_consistency:
        return ""
    return (
        f"judged at the sensor's noise (a {look_voxel(p, depth):.2f} m voxel), its free "
        f"space is firm {firm:.2f} (need {p.min_consistency})"
    )
