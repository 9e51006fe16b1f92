"""Response bodies of the place database. Request bodies are encoded frames
(`application/octet-stream`, the version-1 format of `shared/frame.py`), except `PUT
/links`, which takes `LinkIn` as JSON."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from fleetmap.services.place_db.config import Settings
from fleetmap.services.schemas import ConfigView, Matrix4

#: `GET /config`: the settings in force, tokens left out, the database's and the aligner's
#: URLs without their passwords.
CONFIG = ConfigView(Settings, "PlaceDBConfig", urls=("database", "aligner"))


class Health(BaseModel):
    """Anonymous callers of a secured service see `status` only."""

    status: str
    keyframes: int | None = None
    robots: int | None = None
    pending: int | None = None
    database: str | None = None
    database_ok: bool | None = None
    index_clusters: int | None = None
    index_cluster_max: int | None = None
    storage_errors: int | None = None
    worker_failures: int | None = None
    startup_warning: str | None = None
    access_control: str | None = None


class KeyframeCreated(BaseModel):
    id: int
    robot_id: str
    stamp: float
    created: bool


class RobotInfo(BaseModel):
    robot_id: str
    keyframes: int
    first_stamp: float | None = None
    last_stamp: float | None = None


class Robots(BaseModel):
    robots: list[RobotInfo]


class KeyframeInfo(BaseModel):
    id: int
    stamp: float
    processed: bool


class Keyframes(BaseModel):
    robot_id: str
    keyframes: list[KeyframeInfo]


class StageInfo(BaseModel):
    name: str
    kept: int
    ms: float


class Winner(BaseModel):
    keyframe_id: int
    robot_id: str
    stamp: float
    inliers: int
    matches: int
    gist_distance: float
    bow_distance: float


class QueryAnswer(BaseModel):
    winner: Winner | None
    verified: list[Winner]
    stages: list[StageInfo]
    database_size: int
    total_ms: float


class OverlapPair(BaseModel):
    robot_a: str
    keyframe_a: int
    stamp_a: float
    robot_b: str
    keyframe_b: int
    stamp_b: float
    inliers: int
    matches: int
    source: str = Field(
        "cascade",
        description="cascade: verified by the retrieval cascade (inliers = epipolar "
        "inliers); link: co-visible under a registered map alignment (inliers = feature "
        "points of one keyframe seen by the other's camera, matches = its feature points); "
        "nominated (only with source=nominated): not verified, the BoW-nearest keyframe "
        "pairs where the aligner should look when none is (inliers = matches = 0)",
    )


class LinkIn(BaseModel):
    transform: Matrix4 = Field(
        description="4x4 rigid transform mapping robot_b's map frame into robot_a's"
    )


class LinkOut(BaseModel):
    robot_a: str
    robot_b: str
    link_overlaps: int


class Link(BaseModel):
    robot_a: str
    robot_b: str
    transform: list[list[float]]
    created: float


class OverlapEdge(BaseModel):
    robot_a: str
    robot_b: str
    pairs: int
    best_inliers: int
    total_inliers: int


class Overlaps(BaseModel):
    overlaps: list[OverlapPair] | None = None
    graph: list[OverlapEdge] | None = None
    pending: int


class Deleted(BaseModel):
    robot_id: str
    deleted_keyframes: int


class Retrained(BaseModel):
    clusters: int
    keyframes: int
    cluster_max: int
    cluster_mean: float
    seconds: float


ViewPart = Literal["rgb", "depth"]


class KeyframeView(BaseModel):
    keyframe_id: int
    robot_id: str
    stamp: float
    width: int
    height: int
    intrinsics: dict[str, float]
    T_map_cam: list[list[float]]
    rgb_type: str = Field(description="media type of the colour image (image/jpeg, image/png)")
    rgb: str = Field(description="the colour image as posted, base64")
    depth: str = Field(description="the 16-bit depth PNG as posted, base64")


class Unmerged(BaseModel):
    robot: str
    reason: str


class RobotState(BaseModel):
    robot: str
    keyframes: int
    views: int = Field(description="keyframes stored with their RGB-D view")
    state: Literal["reference", "merged", "unmerged"]
    drift_correction: dict | None = Field(
        None,
        description="once the keyframe graph is solved on this placement: `applied` (the "
        "robot's map bent beyond the closures' noise and was corrected), `moved_median_m`, "
        "`moved_max_m` (how far the correction moved its keyframes from the rigid placement), "
        "`bend_m`, `flagged` (moved beyond what the drift model allows), `rigid_placement`",
    )


class LiveMap(BaseModel):
    version: int = Field(description="changes only when the placement does; 0: none yet")
    reference: str | None = Field(description="the robot whose map frame is the global one")
    transforms: dict[str, list[list[float]]] = Field(
        description="T_ref_R per placed robot R: maps R's map points into the reference's "
        "(row-major 4x4, metres)"
    )
    unmerged: list[Unmerged]
    robots: list[str] = Field(description="every robot known, in order of arrival")
    updated_at: float | None = Field(description="unix time of the last placement change")
    fleet: list[RobotState]
    pairs: list[dict] = Field(description="the merge worker's state of each robot pair")
    overlaps: list[OverlapEdge]
    worker: dict | None = Field(
        None,
        description="the merge worker: `aligning` (the robot pairs being aligned), `due` "
        "(pairs waiting for a free slot), `quiet` (no keyframe for a while: merged pairs get a "
        "last fit on every overlap), `since` (unix time of the change)",
    )
    fleet_graph: dict | None = Field(
        None,
        description="the keyframe pose graph over the placed robots, solved on this placement: "
        "`keyframes`, `closures` (by kind), `intra_robot`, `rejected` (by GNC), `optimise_s`, "
        "`applied` (robots corrected), `skipped` (why no graph was needed), `solved_at`",
    )
