"""The storage interface of the place database: what `PlaceDB` asks of a backend.

`PlaceDB` holds the in-memory index, the overlap worker and the retraining policy; a store
holds everything durable: robots, keyframes (summary columns and the encoded frame),
overlaps, links and codebooks. `SQLiteStore` (`fleetmap.place.sqlite`) is the embedded
default; a second backend implements the same methods.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from fleetmap.frame import Frame


@dataclass(eq=False)
class Pending:
    """One frame waiting for the group commit; the store fills `result` or `error`."""

    robot_id: str
    frame: Frame
    data: bytes
    view: tuple[bytes, bytes] | None = None  # checked colour and depth images, or none
    result: tuple[int, bool] | None = None  # (keyframe id, newly created)
    error: Exception | None = None
    done: bool = False


@dataclass
class IndexRows:
    """A batch of stored keyframes' summary columns, as the index takes them."""

    ids: list[int]
    robots: list[int]
    stamps: list[float]
    gists: np.ndarray  # (N, D) float
    bow_ids: list[np.ndarray]
    bow_counts: list[np.ndarray]
    unprocessed: list[int] = field(default_factory=list)


@dataclass
class OverlapRow:
    """One stored overlap, oriented as stored (kf_a of robot_a)."""

    kf_a: int
    stamp_a: float
    robot_a: int
    kf_b: int
    stamp_b: float
    robot_b: int
    inliers: int  # cascade: verified inliers; link: points of a seen by b
    matches: int  # cascade: SIFT matches; link: points of a
    source: str


# (kf_x, robot_x, kf_y, robot_y, points seen, points) for a link overlap
LinkRow = tuple[int, int, int, int, int, int]
# (kf_b, robot_b, inliers, matches) for a verified cascade winner of one keyframe
WinnerRow = tuple[int, int, int, int]


class Store(Protocol):
    """Durable state of the place database. Robot codes are ints the store assigns."""

    startup_warning: str  # set when the last run may have lost acknowledged keyframes
    storage_errors: int  # stored frames that failed their checksum when read

    def robot_code(self, name: str) -> int | None: ...
    def robot_name(self, code: int) -> str | None: ...
    def robot_count(self) -> int: ...
    def codebook(self) -> np.ndarray | None: ...
    def save_codebook(self, centroids: np.ndarray) -> None: ...
    def index_rows(self, batch: int = 10000) -> Iterator[IndexRows]: ...
    def add_frames(
        self, items: list[Pending], on_commit: Callable[[list[Pending]], None]
    ) -> None: ...
    def frame_bytes(self, kf_id: int) -> bytes: ...
    def keyframe_info(self, kf_id: int) -> dict: ...
    def robots(self) -> list[dict]: ...
    def keyframes(self, code: int, offset: int, limit: int) -> list[dict]: ...
    def robot_keyframe_ids(self, code: int) -> list[int]: ...
    def overlap_rows(self, code_a: int, code_b: int) -> list[OverlapRow]: ...
    def overlap_counts(self) -> list[tuple[int, int, int, int, int]]: ...
    def overlap_total(self) -> int: ...
    def record_overlaps(
        self, kf_id: int, code: int, winners: list[WinnerRow], links: list[LinkRow]
    ) -> bool: ...
    def put_link(self, code_a: int, code_b: int, T_a_b: np.ndarray, rows: list[LinkRow]) -> int: ...
    def links(self, code: int | None = None) -> list[tuple[int, int, np.ndarray, float]]: ...
    def delete_robot(self, code: int, then: Callable[[np.ndarray], None]) -> int: ...
    def view_bytes(self, kf_id: int) -> tuple[bytes, bytes] | None: ...
    def view_ids(self, code: int) -> list[int]: ...
    def live_get(self, key: str) -> str | None: ...
    def live_put(self, key: str, value: str) -> None: ...
    def live_cas(self, key: str, old: str | None, new: str) -> bool: ...
    def ping(self) -> bool: ...
    def size_bytes(self) -> int: ...
    def refuse_writes(self) -> None: ...
    def close(self) -> None: ...
