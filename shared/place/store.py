"""The storage interface of the place database: what `PlaceDB` asks of a backend.

`PlaceDB` holds the in-memory index, the overlap worker and the retraining policy; a store
holds everything durable: robots, keyframes (summary columns and the encoded frame),
overlaps, links and codebooks. `open_store` chooses the backend from where the data lives:
`SQLiteStore` (`fleetmap.place.sqlite`, the embedded default) for a file or folder,
`PostgresStore` (`fleetmap.place.postgres`) for a postgresql:// URL. A store that other
processes write too (`shared`) is also a `SharedStore`: replicas follow it.
"""

from __future__ import annotations

import logging
import threading
import zlib
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from fleetmap.errors import StorageCorrupt, Unavailable, UnknownKeyframe
from fleetmap.frame import Frame

log = logging.getLogger(__name__)


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


class GroupCommit:
    """The group commit of both backends: concurrent callers queue their frames, and whoever
    holds the write lock commits everything queued in one transaction (one fsync for many
    robots), then calls `on_commit(added)` under the lock, so the index sees keyframes in
    commit order. A backend calls `_init_group_commit` and implements `_commit(batch)`,
    which writes a batch in one transaction (the caller holds the write lock) and returns
    the frames newly added."""

    def _init_group_commit(self) -> None:
        self._write_lock = threading.Lock()
        self._pending_lock = threading.Lock()
        self._pending: list[Pending] = []
        self._closed = False

    def _commit(self, batch: list[Pending]) -> list[Pending]:
        raise NotImplementedError

    def add_frames(self, items: list[Pending], on_commit: Callable[[list[Pending]], None]) -> None:
        """Store checked frames durably (the group commit above)."""
        with self._pending_lock:
            self._pending.extend(items)
        with self._write_lock:
            if not items[-1].done:
                with self._pending_lock:
                    batch, self._pending = self._pending, []
                added = self._commit(batch)
                if added:
                    on_commit(added)

    def _refused_when_closed(self, batch: list[Pending]) -> bool:
        """Once closed (shutting down): every frame of the batch answered Unavailable."""
        if self._closed:
            for it in batch:
                it.error, it.done = Unavailable("place database is shutting down"), True
        return self._closed


def checked_frame(store, kf_id: int, row) -> bytes:
    """The encoded frame a backend read for keyframe `kf_id` (`row`: its one column, or
    None where there is no such keyframe), its CRC-32 checked; a failure is counted in
    `store.storage_errors` and logged."""
    if row is None:
        raise UnknownKeyframe(f"Unknown keyframe {kf_id}")
    data = bytes(row[0])
    if len(data) < 4 or zlib.crc32(memoryview(data)[:-4]) != int.from_bytes(data[-4:], "little"):
        store.storage_errors += 1
        log.error("keyframe %d: stored frame fails its CRC-32 (storage corrupted)", kf_id)
        raise StorageCorrupt(
            f"Keyframe {kf_id}: the stored frame fails its checksum (storage corrupted); "
            "the operator should restore it or delete the robot"
        )
    return data


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

    @classmethod
    def from_rows(cls, rows: list[tuple]) -> IndexRows:
        """From rows (id, robot, stamp, gist, bow_ids, bow_counts[, processed]) as stored:
        gist float16, BoW word ids uint32 and counts uint16, little-endian bytes."""
        return cls(
            [r[0] for r in rows],
            [r[1] for r in rows],
            [r[2] for r in rows],
            np.stack([np.frombuffer(r[3], dtype="<f2") for r in rows]),
            [np.frombuffer(r[4], dtype="<u4") for r in rows],
            [np.frombuffer(r[5], dtype="<u2") for r in rows],
            [r[0] for r in rows if len(r) > 6 and not r[6]],
        )


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


#: The URL schemes `open_store` opens with PostgreSQL.
POSTGRES_SCHEMES = ("postgresql://", "postgres://")
#: Seconds to wait for a pooled PostgreSQL connection before answering `Unavailable` (503).
PG_TIMEOUT_S = 5.0
#: The SQLite file `open_store` opens in a folder.
DB_FILE = "place_db.sqlite"


class Store(Protocol):
    """Durable state of the place database. Robot codes are ints the store assigns."""

    startup_warning: str  # set when the last run may have lost acknowledged keyframes
    storage_errors: int  # stored frames that failed their checksum when read
    path: Path | None  # the database file; None for a database server
    where: str  # where the data lives, for messages: a path or host:port/db, no password
    shared: bool  # other processes write the same data: a `SharedStore`

    def exclusive(self, what: str) -> AbstractContextManager[Callable[[], bool]]:
        """Held by one process at a time for `what` ("live map", "retraining"); Conflict
        if another holds it. Yields `held()`: False once the hold was lost."""
        ...

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


class SharedStore(Store, Protocol):
    """A store other processes write too (PostgreSQL): a replica follows their keyframes,
    deletions and codebooks, and claims keyframes for overlap detection from a queue."""

    def index_rows(self, batch: int = 10000, after: int = 0) -> Iterator[IndexRows]: ...
    def deletions_after(self, after: int) -> list[tuple[int, int]]: ...
    def forget_robot(self, code: int) -> None: ...
    def codebook_version(self) -> int: ...
    def pending_count(self) -> int: ...
    def parked(self) -> dict[int, str]: ...
    def claim(self, compute: Callable[[int], tuple | None]) -> int | None: ...


def open_store(url_or_path: str | Path, vocab_id: str, pg_timeout_s: float = PG_TIMEOUT_S) -> Store:
    """The backend where the data lives: a postgresql:// URL opens PostgreSQL (replicas over
    one database; a pooled connection within `pg_timeout_s`, else `Unavailable`); anything
    else SQLite, `DB_FILE` in a folder or else the file named."""
    if isinstance(url_or_path, str) and url_or_path.startswith(POSTGRES_SCHEMES):
        from fleetmap.place.postgres import PostgresStore

        return PostgresStore(url_or_path, vocab_id, timeout_s=pg_timeout_s)
    from fleetmap.place.sqlite import SQLiteStore

    path = Path(url_or_path)
    return SQLiteStore(path / DB_FILE if path.is_dir() else path, vocab_id)
