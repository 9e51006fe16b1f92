"""The alignment's data types and parameters: numpy only (no torch, no Open3D)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from fleetmap.geometry import apply
from fleetmap.mapcloud import MAX_DEPTH_M

if TYPE_CHECKING:
    from fleetmap.estimators import MLPEstimator


@dataclass(frozen=True)
class SecondLook:
    """The second look's settings (`fleetmap.align.second_look`)."""

    views: int = 6  # per robot, spread over the first look's views
    max_tilt: int = 4
    # SIFT features per simulated tilt. On the kept recall pairs (docs/ALIGNER.md): 120
    # lost three of the four HoloLens second-look merges; 320 kept them and merged one
    # more (31% shared, 1.1 cm) at 1.3x the cost of 200 (24 against 18.5 s for 12 views
    # on a loaded machine); SUN3D's unpinned merges and the cross pairs stayed refused
    per_view: int = 320
    ratio: float = 0.85
    # the ratio test's second nearest at least this many pixels from the nearest's keypoint
    # (`fleetmap.matching.distinct_second`: ASIFT describes one point under several tilts).
    # HoloLens window pairs walked the other way, matches within 8 cm of the truth over 6 x 6
    # views: 1.5 px 40 / 11 / 12 / 9, 3 px 50 / 15 / 15 / 13, 6 px 55 / 16 / 17 / 13, plain
    # ratio test (0) 31 / 7 / 10 / 3 (docs/ALIGNER.md, session 22)
    distinct_px: float = 4.0

    def __post_init__(self) -> None:
        if self.views < 1 or self.max_tilt < 1 or self.per_view < 1:
            raise ValueError("the second look needs views >= 1, max_tilt >= 1, per_view >= 1")
        if not 0 < self.ratio <= 1:
            raise ValueError("the second look's ratio must lie in (0, 1]")
        if not self.distinct_px >= 0:
            raise ValueError("the second look's distinct_px must be 0 (off) or more")


@dataclass(frozen=True)
class GeometricLook:
    """The third look's settings (`fleetmap.align.geometric_look`)."""

    # FPFH voxel as a share of the views' median depth (FPFH radius five voxels: a quarter
    # of the viewing distance, the same share of what a camera frames at any scale)
    voxel_rel: float = 0.05
    # RANSAC seeds (every other one with mutual feature matches); on the recall bench's
    # HoloLens and SUN3D windows the right basin came from 2-14 of 20
    seeds: int = 16
    iterations: int = 100_000
    # starts from the maps' dominant planes (manhattan.py): of the 24 rotations between
    # the two maps' plane frames and their best translations, those where the most
    # occupied cells meet (0: none)
    plane_starts: int = 16
    # firm free-space consistency each way, judged at half a voxel (2.5% of the depth) or
    # at `noise_k` times the spread the two robots' own depth readings show at each depth
    # (`fleetmap.depth_noise`), whichever is wider
    min_consistency: float = 0.9
    noise_k: float = 2.0
    # grey levels of the points that meet (within half a voxel), Pearson
    min_correlation: float = 0.5
    # each basin refined by coloured ICP too (`hypotheses.colour_icp`), both judged:
    # opt-in. Recall seed 80 and the suite (docs/ALIGNER.md, session 52): two refusals
    # become merges 5.2 and 6.4 cm off the truth (loose), no wrong merge, none made right
    colour_refine: bool = False

    def __post_init__(self) -> None:
        if self.seeds < 1 or self.iterations < 1 or not self.voxel_rel > 0 or self.plane_starts < 0:
            raise ValueError(
                "the third look needs seeds >= 1, iterations >= 1, voxel_rel > 0, plane_starts >= 0"
            )
        if not self.noise_k >= 0:
            raise ValueError(f"the third look's noise_k must be 0 (off) or more: {self.noise_k}")
        if not (0 <= self.min_consistency <= 1 and -1 <= self.min_correlation <= 1):
            raise ValueError("min_consistency must lie in [0, 1], min_correlation in [-1, 1]")


@dataclass(frozen=True)
class AlignParams:
    """Gate thresholds in metres; see the module docstring for the stages."""

    ransac_tol_m: float = 0.08
    min_inliers: int = 12
    min_spread_m: float = 0.15
    max_holdout_m: float = 0.08
    hypotheses: int = 6  # disjoint consensus sets of the pooled verified matches
    raw_consensus: bool = False  # second look: hypotheses of the raw matches pooled (opt-in)
    pair_min_support: int = 4  # a pair's raw matches give a hypothesis with this support
    max_candidates: int = 40  # distinct hypotheses scored at the coarse scale
    dedupe_m: float = 0.25  # hypotheses closer than this (RMS over B's cloud) share one ICP basin
    refine: int = 4  # best coarse hypotheses refined at the fine scale
    voxel_m: float = 0.03
    coarse_voxel_m: float = 0.08
    min_consistency: float = 0.7  # free-space supports / (supports + conflicts)
    min_overlap: float = 0.1  # share of B's cloud on A's surfaces
    ambiguity: float = 0.9  # a rival with this share of the best score makes it ambiguous
    rival_m: float = 0.3
    rival_deg: float = 10.0
    use_icp: bool = True
    colour_icp: bool = True
    # coloured ICP on B's grey levels matched to A's where the maps meet and the cameras
    # differ (`hypotheses.exposure_matched`: recall seed 111 through x0.6, 2.59 -> 2.10 cm
    # mean; docs/ALIGNER.md, sessions 61-62)
    match_exposure: bool = True
    try_mlp: bool = True
    min_spread_rel: float = 0.075  # or this share of the views' median depth, if less
    decisive_consistency: float = 0.95  # firm free-space consistency: geometry that decides
    # under `decisive_consistency` firm, the grey levels where the maps meet must correlate
    # this much (Pearson): surfaces that do not look alike at all are not one place
    # (pipeline._colour_gate; right merges 0.46-0.94, maps that bend the lowest)
    min_colour_correlation: float = 0.3
    # refused pairs looked at again with ASIFT (second_look.py); its merges must be pinned
    # by the matches (pinning.unpinned: without, SUN3D windows merged 11-15 cm off)
    second_look: bool = True
    second: SecondLook = SecondLook()
    # refused by both: the maps' geometry proposes, free space and colour decide
    # (geometric_look.py)
    geometric_look: bool = True
    geometric: GeometricLook = GeometricLook()
    # the nearest scene (median depth of the views, metres) judged at the lengths above, the
    # rooms' (set on the HoloLens lounge, 1.7-2.8 m, and SUN3D, 2.3-3.5 m); a nearer scene
    # has them shrunk in proportion (`at_depth`). 1 m (the TUM desk) until session 49: SUN3D
    # at 0.4 of its size (1.1-1.4 m) through a D435 merged 17 cm off. 2.8 m moved the rooms
    # themselves (SUN3D's own fit at 2.3 m 3 -> 10 cm; the lounge merged onto the study
    # room); at 2 m every real room pair merges as before (docs/ALIGNER.md, "Session 49")
    reference_depth_m: float = 2.0
    # the farthest: SUN3D's study room, whose robot_a sees it from 3.3-3.5 m (the HoloLens
    # lounge 1.7-2.8 m); a farther scene has them grown in proportion (`at_depth`)
    far_depth_m: float = 3.5
    # the views' clouds (ICP, overlap, free space, the depth noise) leave out readings
    # farther than this; in a larger scene they may reach `max_depth_rel` times its median
    # depth, as far as the robots' readings agree within the coarse voxel
    # (`cloud_depth_cap`, `pipeline._reach`)
    max_depth_m: float = MAX_DEPTH_M
    max_depth_rel: float = 2.0

    def __post_init__(self) -> None:
        if not 0 < self.reference_depth_m <= self.far_depth_m:
            raise ValueError(
                "reference_depth_m and far_depth_m must be depths in metres, the first no farther"
            )
        if not (self.max_depth_m > 0 and self.max_depth_rel >= 0):
            raise ValueError("max_depth_m must be a positive depth, max_depth_rel 0 or more")

    def at_depth(self, depth_m: float) -> AlignParams:
        """These parameters for views whose median depth is `depth_m`: nearer than
        `reference_depth_m`, every length (the RANSAC tolerance, the held-out residual, the
        spread, the voxels and with them every ICP distance and free-space margin, the
        distances that make hypotheses one or rivals) x depth / reference; farther than
        `far_depth_m`, x depth / far; the counts, shares and angles as they are; between
        the two, where the lengths were set and measured, unchanged.

        A camera nearer its scene frames less of it and measures it finer (the features'
        sideways error grows as depth, the depth noise as its square), so a length set for a
        room is a share of a desk that would not be one of a room. The TUM desk seen from 0.4
        m (the recording with its depths and poses x 0.4, an exact copy of the scene at 0.4
        of the size): the coarse ICP at 8 cm voxels with 32 cm reach slid the best
        hypothesis 45 cm / 40 deg from the truth, and the gate refused (free-space
        consistency 0.55) a pair it merges from 1 m at 2.6 cm; the SUN3D study room at 0.4
        of its size (1.1-1.4 m) through a D435 and another camera, judged at a room's lengths,
        merged 17 cm off (the pose tolerances alone in proportion: the same basin, found on
        the maps' geometry at 3 cm voxels). A farther scene is the same
        case the other way: 8 cm is half as much of a room twice the size, whose readings
        spread at least twice as far (a sensor's noise grows as the depth or faster), and
        the chance that wrong matches agree within a tolerance is that of the tolerance's
        share of the scene, so lengths in proportion keep it. The HoloLens walk at twice its
        size (docs/ALIGNER.md, session 45): see there."""
        if not depth_m > 0:
            return self
        k = min(depth_m / self.reference_depth_m, 1.0) * max(depth_m / self.far_depth_m, 1.0)
        if k == 1:
            return self
        lengths = ("ransac_tol_m", "min_spread_m", "max_holdout_m", "dedupe_m", "voxel_m")
        lengths += ("coarse_voxel_m", "rival_m")
        return replace(self, **{name: k * getattr(self, name) for name in lengths})

    def cloud_depth_cap(self, depth_m: float) -> float:
        """How far (metres) the views' clouds may reach for a scene of median depth
        `depth_m`: `max_depth_m`, or `max_depth_rel` x the median where that is farther
        (beyond `max_depth_m` only as far as the robots' readings agree within the coarse
        voxel: `pipeline._reach`). The 6 m cap was set on rooms seen from 1-3 m (a
        Kinect-class sensor's useful range), where it never cuts inside twice the median
        depth; a larger room seen by a sensor that reaches it lost half of each view to it:
        the HoloLens walk at twice its size (median 5.1 m, seed 61), hl_a[15:75] /
        hl_b[120:180] (31% shared), was refused with "the maps overlap on 0.09 of B's
        cloud" and merges 2.1 cm from the truth (at the recording's size) with the clouds
        to 10.2 m (docs/ALIGNER.md, session 43)."""
        return max(self.max_depth_m, self.max_depth_rel * depth_m)

    def spread_needed(self, depth_m: float) -> float:
        """The inliers' spread (metres) the gate needs for views whose median depth is
        `depth_m`: `min_spread_m`, or less for a nearer scene (0.075 x depth: 0.15 m at
        2 m, 7.5 cm for a desk seen from a metre). The spread guards the rotation: its
        error grows as depth noise over spread, and a depth camera's noise and the scene
        it frames both shrink with distance."""
        return min(self.min_spread_m, self.min_spread_rel * depth_m)

    def decisive(self, firm_consistency: float, overlap: float) -> bool:
        """Does the maps' geometry decide on its own? At most one point in twenty firmly in
        space the other robot saw empty (`Hypothesis.firm_consistency`), and each map's
        share on the other's (`overlap`: the smaller of the two) at least twice what the
        gate asks. Both ways, because a small map laid on a large one's planes fits
        anywhere (four TUM desk frames on the SUN3D room: 48% of the desk on the room at
        0.95, 6% of the room on the desk). Where it does, it stands in for the free-space
        gate and halves the visual inliers needed: a wide baseline may leave a handful of
        right matches (SUN3D's two recordings: 8 of 489 agree with the truth), while right
        alignments score 0.956-1.00 firm and look-alike places up to 0.87
        (docs/ALIGNER.md)."""
        return firm_consistency >= self.decisive_consistency and overlap >= 2 * self.min_overlap


DEFAULT_ALIGN = AlignParams()


@dataclass
class Hypothesis:
    T_a_b: np.ndarray
    support: int
    source: str = "pooled"
    fitness: float = 0.0  # share of B's cloud within 2 voxels of A's
    supports: int = 0  # free-space check, both ways
    conflicts: int = 0
    firm_conflicts: int = 0  # conflicts that hold sideways too (`free_space_check`)

    @property
    def consistency(self) -> float:
        return self.supports / max(self.supports + self.conflicts, 1)

    @property
    def firm_consistency(self) -> float:
        return self.supports / max(self.supports + self.firm_conflicts, 1)

    @property
    def score(self) -> float:
        """Net agreement: surface points seen where the other robot saw a surface, less
        those put where the other robot saw empty space."""
        return float(self.supports - self.conflicts)

    def summary(self) -> dict:
        return {
            "source": self.source,
            "support": self.support,
            "icp_fitness": round(self.fitness, 4),
            "consistency": round(self.consistency, 4),
            "firm_consistency": round(self.firm_consistency, 4),
            "score": round(self.score, 1),
        }


@dataclass
class AlignResult:
    """Outcome: merged or not (with the reason), T_a_b maps B's map frame into A's."""

    merged: bool
    reason: str
    T_a_b: np.ndarray | None = None
    method: str = ""
    correspondences: int = 0
    inliers: int = 0
    holdout_m: float = float("nan")
    fitness: float = 0.0
    mlp_holdout_m: float | None = None
    mlp: MLPEstimator | None = field(default=None, repr=False)
    hypotheses: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    scene_depth_m: float = float("nan")  # the views' median depth: the gate's lengths follow it

    def to_dict(self) -> dict:
        d = {
            "merged": self.merged,
            "reason": self.reason,
            "method": self.method,
            "correspondences": self.correspondences,
            "inliers": self.inliers,
            "holdout_residual_m": _num(self.holdout_m),
            "icp_fitness": self.fitness,
            "mlp_holdout_residual_m": _num(self.mlp_holdout_m),
            "hypotheses": self.hypotheses,
            "seconds": self.seconds,
            "scene_depth_m": _num(self.scene_depth_m),
        }
        if self.T_a_b is not None:
            d["transform"] = self.T_a_b.tolist()
        if self.mlp is not None:
            d["affine"] = self.mlp.affine_.tolist()
        return d

    def map_points(self, points_b: np.ndarray) -> np.ndarray:
        """B's map points into A's frame with the chosen model."""
        if self.mlp is not None:
            return self.mlp.transform(points_b)
        return apply(self.T_a_b, points_b)


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


def unique_views(pairs, side: int) -> list:
    """The distinct views (by identity) of one side (0: robot A, 1: robot B) of the pairs."""
    seen, out = set(), []
    for pr in pairs:
        v = pr[side]
        if id(v) not in seen:
            seen.add(id(v))
            out.append(v)
    return out
