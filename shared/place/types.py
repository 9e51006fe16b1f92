"""The place database's data types: light, numpy only (no faiss, no SQLite)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fleetmap.matching import DEFAULT_MATCH_PARAMS, MatchParams, Verification


@dataclass(frozen=True)
class CascadeParams:
    """Cascade settings; distances are between unit-length GIST vectors (0..2)."""

    m_clusters: int = 64
    gist_threshold: float = 0.75
    max_candidates: int = 300
    # inverted file beside the GIST clusters (docs/PLACE_DB.md says why these values)
    ivf_words: int = 8  # the query's most informative words whose postings are read
    ivf_candidates: int = 12  # keyframes it may add to the GIST stage's (= max_verify)
    bow_threshold: float = 0.92
    max_verify: int = 12
    max_verify_per_robot: int = 4
    match: MatchParams = DEFAULT_MATCH_PARAMS


DEFAULT_CASCADE = CascadeParams()


@dataclass
class Stage:
    name: str
    kept: int
    ms: float


@dataclass
class Candidate:
    """A stored keyframe the cascade considered; `robot_code` is the store's integer code
    of its robot (names are for the API: `PlaceDB.robot_name`)."""

    kf_id: int
    robot_code: int
    stamp: float
    gist_distance: float
    bow_distance: float = 1.0
    verification: Verification | None = None


@dataclass
class CascadeResult:
    """The winner (or None), every verified candidate (most inliers first), the stages."""

    winner: Candidate | None
    verified: list[Candidate]
    stages: list[Stage]
    database_size: int
    total_ms: float = 0.0


@dataclass
class Filter:
    """Which stored keyframes a query may return."""

    robots: set[int] | None = None  # only these robot codes
    exclude_robots: set[int] = field(default_factory=set)
    max_stamp: float | None = None  # only keyframes strictly older (loop closure)

    def mask(self, robots: np.ndarray, stamps: np.ndarray) -> np.ndarray:
        """Which of the keyframes with these robot codes and stamps pass, shape (N,)."""
        keep = np.ones(len(robots), bool)
        if self.robots is not None:
            keep &= np.isin(robots, list(self.robots))
        if self.exclude_robots:
            keep &= ~np.isin(robots, list(self.exclude_robots))
        if self.max_stamp is not None:
            keep &= stamps < self.max_stamp
        return keep


@dataclass
class Overlap:
    """A verified keyframe pair between two robots, oriented robot_a -> robot_b."""

    robot_a: str
    kf_a: int
    stamp_a: float
    robot_b: str
    kf_b: int
    stamp_b: float
    inliers: int
    matches: int
    source: str = "cascade"  # or "link": co-visible under a registered map alignment


@dataclass(frozen=True)
class RetrainPolicy:
    """When the coarse codebook no longer fits the stored GISTs (thesis Fig. 2.12)."""

    enabled: bool = True
    min_keyframes: int = 2000
    max_mean_list: int = 256  # retrain when keyframes per cluster exceed this
    max_imbalance: float = 10.0  # or when the largest list exceeds this x the mean

    def target_clusters(self, n: int) -> int:
        return int(np.clip(2 * np.sqrt(n), 8, 8192))
