"""The fleet level's typed state: a pairwise `Fit` (the aligner's answer), the merge
worker's `PairState` of a robot pair, and a `Placement` of the fleet in the reference
robot's frame; the edge a fit adds to the placement (`edge`).

A transform between robots is, in memory, a float64 ndarray of shape (4, 4) named `T_a_b`
(it maps points of B's map frame into A's) or `T_ref_r`; on the wire and in the store it
is the row-major nested list of JSON (`transform_to_json`, `transform_from_json`). It is
inverted in one place, `fleetmap.geometry.invert`. The fleet stages' parameters live here
once (`ViewParams`, `MergeParams`): the CLI's defaults read them. Imports nothing heavy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, TypedDict

import numpy as np

from fleetmap.keyframes import KeyframePolicy


@dataclass(frozen=True)
class ViewParams:
    """Which RGB-D views of a robot pair go to the aligner (`fleetmap.fleet.view_choice`):
    at most `max_views` per robot, the verified keyframes first, then those whose look-at
    points lie within `radius_m` of a verified one's."""

    max_views: int = 12
    radius_m: float = 3.0
    # a refused pair is aligned again from the views along its best overlap's path, within
    # the path over which the fleet graph's drift model (1 deg/m of yaw, 1 % scale:
    # `GraphParams`) bends a map by the aligner's match tolerance (8 cm): 2.5 m
    # (`view_choice.local_views`)
    local_path_m: float = 2.5


#: The finest merged-map voxel: an RGB-D camera's depth comes in steps of about a
#: millimetre (a 16-bit reading in mm or 0.2 mm), so a finer voxel thins nothing, and far
#: finer ones overflow Open3D's voxel grid (1e-12 m: "voxel_size is too small" after the
#: whole merge had run)
MIN_VOXEL_M = 0.001


@dataclass(frozen=True)
class MergeParams:
    """What `fleetmap merge` runs with beside its robots and services (the CLI's defaults;
    report.json's `parameters`). `voxel_m` is also `fleetmap map`'s merged.ply voxel."""

    keyframes: KeyframePolicy = KeyframePolicy()
    views: ViewParams = ViewParams()
    voxel_m: float = 0.03  # merged.ply's voxel size
    pcd: bool = False  # also write merged.pcd
    correct_drift: bool = True  # the keyframe pose graph over the fleet (`fleetmap.fleet`)

    def __post_init__(self) -> None:
        if not self.voxel_m >= MIN_VOXEL_M:  # NaN too
            raise ValueError(f"voxel_m must be at least {MIN_VOXEL_M} m, got {self.voxel_m}")


DEFAULT_VIEWS = ViewParams()
DEFAULT_MERGE = MergeParams()


def transform_to_json(T: np.ndarray) -> list[list[float]]:
    """The wire form of a 4x4 transform: row-major nested lists."""
    return np.asarray(T, np.float64).tolist()


def transform_from_json(rows) -> np.ndarray:
    """A 4x4 transform from its wire form: float64 ndarray of shape (4, 4)."""
    return np.array(rows, np.float64)


def edge(T_a_b: np.ndarray, inliers: int) -> dict:
    """A gated fit as an edge of the placement: {"T_a_b": (4, 4) ndarray, "inliers": int}
    (`fleetmap.fleet.placement`, `cycles`, `correct`, the g2o file)."""
    return {"T_a_b": T_a_b, "inliers": inliers}


def pair_key(a: str, b: str) -> str:
    """The key of a robot pair's state: "A|B", names sorted."""
    return "|".join(sorted((a, b)))


#: The pair state's copy of its fit (`Fit.state_fields`).
FIT_FIELDS = ("reason", "inliers", "holdout_residual_m", "method", "seconds")


@dataclass
class Fit:
    """The aligner's answer for robot pair (A, B) (`POST /align`), typed where the fleet
    reads it. `answer` keeps every figure as the aligner sent it (its order too; hypotheses
    left out), for report.json's `fits`."""

    robot_a: str
    robot_b: str
    merged: bool
    T_a_b: np.ndarray | None  # (4, 4): B's map frame into A's; None when refused
    inliers: int | None
    method: str | None
    reason: str | None
    holdout_residual_m: float | None
    seconds: float | None
    views: list[int] | None = None  # views of A and of B sent
    answer: dict = field(default_factory=dict, repr=False)
    link_overlaps: int | None = None  # co-visible keyframe pairs the link recorded

    @classmethod
    def from_json(cls, d: dict, robot_a: str | None = None, robot_b: str | None = None) -> Fit:
        """From the aligner's answer (robots given) or a report's `fits` item."""
        answer = {k: v for k, v in d.items() if k not in ("robot_a", "robot_b", "views")}
        answer.pop("hypotheses", None)
        links = answer.pop("link_overlaps", None)
        T = d.get("transform")
        return cls(
            robot_a=d["robot_a"] if robot_a is None else robot_a,
            robot_b=d["robot_b"] if robot_b is None else robot_b,
            merged=bool(d["merged"]),
            T_a_b=None if T is None else transform_from_json(T),
            **{k: d.get(k) for k in FIT_FIELDS},
            views=d.get("views"),
            answer=answer,
            link_overlaps=links,
        )

    def to_json(self) -> dict:
        """report.json's `fits` item: robots, views, then the aligner's answer."""
        typed = {k: getattr(self, k) for k in FIT_FIELDS} | {"merged": self.merged}
        if self.T_a_b is not None:
            typed["transform"] = transform_to_json(self.T_a_b)
        out = {"robot_a": self.robot_a, "robot_b": self.robot_b, "views": self.views}
        out |= {k: typed.get(k, v) for k, v in self.answer.items()}
        if self.link_overlaps is not None:
            out["link_overlaps"] = self.link_overlaps
        return out

    def edge(self) -> dict:
        """This fit as an edge of the placement (a merged fit)."""
        return edge(self.T_a_b, self.inliers)

    def state_fields(self) -> dict:
        """What a pair state keeps of its fit (FIT_FIELDS; a merged one's `transform`
        besides, `transform_to_json(T_a_b)`)."""
        return {k: getattr(self, k) for k in FIT_FIELDS}


class PairState(TypedDict, total=False):
    """The merge worker's state of one robot pair, as stored (the "pairs" row: JSON keyed
    `pair_key(a, b)`) and served (`GET /map`'s `pairs`). A dict on purpose: the stored JSON
    is read and written as it is, unknown keys kept; the keys are these."""

    robot_a: str  # the pair's robots, names sorted
    robot_b: str
    status: Literal["merged", "refused", "no_views"]
    evidence: int  # the verified (cascade) overlaps it was aligned on; 0 on nominated pairs
    at: float  # unix time of the attempt
    nominated: list[int]  # the robots' keyframe counts when tried on nominated pairs
    since: list[int | None]  # each robot's incarnation (first keyframe id) when aligned
    attempts: int
    budget: int  # views per robot the fit could use
    views: list[int]  # views of A and of B sent (no_views: views stored)
    reason: str | None  # the aligner's (or why no view was sent)
    inliers: int | None
    holdout_residual_m: float | None
    method: str | None
    seconds: float | None
    transform: list[list[float]]  # merged: T_a_b on the wire (B's map frame into A's)
    refusals: int  # refused: how many times in a row (its back-off doubles)
    last_refusal: str  # merged, then refused by the gate: the merge kept, the reason
    kept: str  # merged, then a worse refit: the earlier fit kept, why
    surface_rmse_m: float  # the fit's distance to the surfaces of the whole maps


def state_transform(st: PairState) -> np.ndarray:
    """A merged pair's T_a_b."""
    return transform_from_json(st["transform"])


@dataclass
class Placement:
    """Robots placed in the reference robot's map frame: `T_ref` maps each placed robot's
    map points into the reference's (T_ref_r, (4, 4)). Stored as the "map" row (`to_json`,
    `from_json`); `chain` (the robots each placement went through) is not stored."""

    reference: str | None = None
    T_ref: dict[str, np.ndarray] = field(default_factory=dict)
    flagged: dict[str, str] = field(default_factory=dict)  # robot -> why it is not placed
    version: int = 0  # raised whenever the placement changes; 0: none yet
    updated_at: float | None = None
    optimised: bool | None = None  # the pose graph reconciled cycles of fits
    links: list[list] = field(default_factory=list)  # [a, b, inliers] of the fits used
    chain: dict[str, list[str]] = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        out = {
            "reference": self.reference,
            "transforms": {r: transform_to_json(T) for r, T in self.T_ref.items()},
            "flagged": self.flagged,
            "version": self.version,
            "updated_at": self.updated_at,
        }
        if self.optimised is not None:
            out["optimised"] = self.optimised
        return out | {"edges": self.links}

    @classmethod
    def from_json(cls, d: dict) -> Placement:
        """From the stored "map" row ({} before the first placement)."""
        return cls(
            reference=d.get("reference"),
            T_ref={r: transform_from_json(T) for r, T in d.get("transforms", {}).items()},
            flagged=dict(d.get("flagged", {})),
            version=d.get("version", 0),
            updated_at=d.get("updated_at"),
            optimised=d.get("optimised"),
            links=[list(e) for e in d.get("edges", [])],
        )

    def same_as(self, other: Placement) -> bool:
        """The same reference, flags and transforms (within 1e-9): no new version."""
        if self.reference != other.reference or set(self.T_ref) != set(other.T_ref):
            return False
        if self.flagged != other.flagged:
            return False
        return all(np.allclose(self.T_ref[r], T, atol=1e-9) for r, T in other.T_ref.items())
