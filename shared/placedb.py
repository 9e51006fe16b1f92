"""The place database: durable keyframe storage (SQLite, WAL) and the live place index.

A keyframe is acknowledged only after its transaction is committed with
`synchronous=FULL`, so an acknowledged keyframe survives a crash of the process or the
machine. On start the in-memory index is rebuilt from the small per-keyframe columns
(GIST and BoW); full frames (local features) stay on disk until a candidate needs them.

Overlaps between robots are found incrementally: each new keyframe is queued, and a
background worker runs the cascade against the other robots' keyframes and records the
verified winner per robot. Keyframes not yet processed when the process stopped are
re-queued on start, so a crash loses no overlap either.
"""

from __future__ import annotations

import logging
import os
import queue
import sqlite3
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.errors import (
    BadInput,
    Conflict,
    StorageCorrupt,
    Unavailable,
    UnknownKeyframe,
    UnknownRobot,
)
from shared.frame import Frame, check_robot_id, decode
from shared.geometry import check_transform
from shared.retrieval import (
    DEFAULT_CASCADE,
    CascadeParams,
    CascadeResult,
    Filter,
    PlaceIndex,
    run_cascade,
    sparse_covisibility,
)
from shared.vocabulary import Vocabulary

log = logging.getLogger(__name__)

SCHEMA_VERSION = 2  # 2: links table, overlaps.source
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS robots (
    id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, created REAL NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    robot INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    stamp REAL NOT NULL, created REAL NOT NULL, processed INTEGER NOT NULL DEFAULT 0,
    gist BLOB NOT NULL, bow_ids BLOB NOT NULL, bow_counts BLOB NOT NULL, data BLOB NOT NULL,
    UNIQUE (robot, stamp));
CREATE INDEX IF NOT EXISTS keyframes_unprocessed ON keyframes(processed) WHERE processed = 0;
CREATE TABLE IF NOT EXISTS overlaps (
    kf_a INTEGER NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
    kf_b INTEGER NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
    robot_a INTEGER NOT NULL, robot_b INTEGER NOT NULL,
    inliers INTEGER NOT NULL, matches INTEGER NOT NULL, created REAL NOT NULL,
    source TEXT NOT NULL DEFAULT 'cascade',
    PRIMARY KEY (kf_a, kf_b));
CREATE INDEX IF NOT EXISTS overlaps_robots ON overlaps(robot_a, robot_b);
CREATE TABLE IF NOT EXISTS links (
    robot_a INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    robot_b INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    transform BLOB NOT NULL, created REAL NOT NULL, PRIMARY KEY (robot_a, robot_b));
CREATE TABLE IF NOT EXISTS codebooks (
    id INTEGER PRIMARY KEY AUTOINCREMENT, created REAL NOT NULL, n_clusters INTEGER NOT NULL,
    dim INTEGER NOT NULL, centroids BLOB NOT NULL);
"""


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


@dataclass(eq=False)
class _Pending:
    """One frame waiting for the group commit."""

    robot_id: str
    frame: Frame
    data: bytes
    result: tuple[int, bool] | None = None
    error: Exception | None = None
    done: bool = False


@dataclass(frozen=True)
class RetrainPolicy:
    """When the coarse codebook no longer fits the stored GISTs (thesis Fig. 2.12)."""

    enabled: bool = True
    min_keyframes: int = 2000
    max_mean_list: int = 256  # retrain when keyframes per cluster exceed this
    max_imbalance: float = 10.0  # or when the largest list exceeds this x the mean

    def target_clusters(self, n: int) -> int:
        return int(np.clip(2 * np.sqrt(n), 8, 8192))


class PlaceDB:
    """Keyframes of a fleet, their place index and the overlaps found between robots."""

    def __init__(
        self,
        path: str | Path,
        vocabulary: Vocabulary,
        params: CascadeParams = DEFAULT_CASCADE,
        retrain: RetrainPolicy | None = None,
        background: bool = True,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # looked at before SQLite opens the database (opening writes a new log)
        wal, marker = Path(str(self.path) + "-wal"), Path(str(self.path) + ".open")
        lost_log = marker.exists() and not (wal.exists() and wal.stat().st_size > 0)
        self.vocabulary = vocabulary
        self.params = params
        self.retrain_policy = retrain or RetrainPolicy()
        self._write_lock = threading.Lock()
        self._pending_lock = threading.Lock()
        self._pending: list[_Pending] = []
        self._local = threading.local()
        self._db = self._connect()
        self._init_schema()
        self._robot_ids: dict[str, int] = {}
        self._centres: dict[int, np.ndarray] = {}  # keyframe id -> map-point centre (links)
        self._robot_names: dict[int, str] = {}
        self.index = PlaceIndex(self._initial_codebook(), vocabulary.n_words)
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._retraining = threading.Lock()
        self._closed = False
        self.storage_errors = 0  # stored frames that failed their checksum when read
        self.failures = 0  # keyframes whose overlap detection raised
        self.parked: dict[int, str] = {}  # keyframe -> reason, the last 100
        self._stopping = False
        self._check_last_close(lost_log)
        self._load()
        self._worker = None
        if background:
            self._worker = threading.Thread(target=self._work, name="overlap-worker", daemon=True)
            self._worker.start()

    # --- storage --------------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        try:
            db = sqlite3.connect(
                self.path, check_same_thread=False, isolation_level=None, timeout=30.0
            )
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.execute("PRAGMA foreign_keys=ON")
        except sqlite3.DatabaseError as exc:
            raise StorageCorrupt(
                f"{self.path} is not a readable SQLite database ({exc}): restore it from a "
                "backup or move it away to start an empty one"
            ) from exc
        return db

    def _note_acknowledged(self, kf_id: int) -> None:
        """Record, outside SQLite, the newest keyframe id committed: at the next start a
        database that has lost acknowledged keyframes (its write-ahead log deleted or
        truncated) is told from one that has not."""
        path = Path(str(self.path) + ".acked")
        tmp = path.with_suffix(".acked.tmp")
        with open(tmp, "w") as f:
            f.write(str(kf_id))
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)

    def _check_acknowledged(self) -> str:
        path = Path(str(self.path) + ".acked")
        try:
            acked = int(path.read_text())
        except (OSError, ValueError):
            return ""
        row = self._db.execute("SELECT seq FROM sqlite_sequence WHERE name='keyframes'").fetchone()
        have = int(row[0]) if row else 0
        if have >= acked:
            return ""
        return (
            f"{self.path} has keyframe ids up to {have} but ids up to {acked} were "
            "acknowledged: keyframes were lost (write-ahead log deleted or truncated?); "
            "the robots should re-send theirs (identical frames are accepted again)"
        )

    def _check_last_close(self, lost_log: bool) -> None:
        """Say so when the last run did not close cleanly and its write-ahead log is gone:
        keyframes acknowledged since the last checkpoint may be lost. A clean close
        checkpoints the log into the database and removes the marker file `DB.open`; the
        marker lives outside the database, where losing the log cannot take it along."""
        self.startup_warning = ""
        marker = Path(str(self.path) + ".open")
        with self._write_lock:
            try:
                bad = self._db.execute("PRAGMA quick_check").fetchone()[0]
            except sqlite3.DatabaseError as exc:
                bad = str(exc)
        if bad != "ok":
            raise StorageCorrupt(f"{self.path} fails its integrity check: {bad}")
        self.startup_warning = self._check_acknowledged()
        has_acked = Path(str(self.path) + ".acked").exists()
        if lost_log and not has_acked:  # no record of what was acknowledged: the heuristic
            self.startup_warning = (
                f"{self.path} was not closed cleanly (opened {marker.read_text().strip()}) "
                "and its write-ahead log is missing or empty: keyframes acknowledged since "
                "the last checkpoint may be lost; compare with the robots' own records"
            )
        if self.startup_warning:
            log.error("%s", self.startup_warning)
        with open(marker, "w") as f:
            f.write(time.strftime("%Y-%m-%dT%H:%M:%S%z"))
            f.flush()
            os.fsync(f.fileno())

    def _reader(self) -> sqlite3.Connection:
        """One read connection per thread: WAL readers never block the writer."""
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = self._connect()
        return conn

    def _init_schema(self) -> None:
        with self._write_lock:
            self._migrate()
            self._db.executescript(SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
            if row is None:
                self._db.execute(
                    "INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),)
                )
                self._db.execute(
                    "INSERT INTO meta VALUES ('vocab_id', ?)", (self.vocabulary.vocab_id,)
                )
            elif int(row[0]) != SCHEMA_VERSION:
                raise BadInput(
                    f"{self.path}: schema version {row[0]}, this build uses {SCHEMA_VERSION}"
                )
            vid = self._db.execute("SELECT value FROM meta WHERE key='vocab_id'").fetchone()[0]
            if vid != self.vocabulary.vocab_id:
                raise BadInput(
                    f"{self.path} was built with vocabulary {vid}, but "
                    f"{self.vocabulary.vocab_id} is loaded"
                )

    def _migrate(self) -> None:
        """Schema 1 -> 2: overlaps gain a source column, links appear (by SCHEMA)."""
        has_meta = self._db.execute(
            "SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'"
        ).fetchone()
        if not has_meta:
            return
        row = self._db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        if row is not None and int(row[0]) == 1:
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute(
                "ALTER TABLE overlaps ADD COLUMN source TEXT NOT NULL DEFAULT 'cascade'"
            )
            self._db.execute("UPDATE meta SET value='2' WHERE key='schema_version'")
            self._db.execute("COMMIT")
            log.info("%s: schema migrated from version 1 to 2", self.path)

    def _initial_codebook(self) -> np.ndarray:
        row = self._db.execute(
            "SELECT n_clusters, dim, centroids FROM codebooks ORDER BY id DESC LIMIT 1"
        ).fetchone()
        if row is None:
            return self.vocabulary.gist_centroids
        return np.frombuffer(row[2], dtype=np.float32).reshape(row[0], row[1])

    def _load(self) -> None:
        t = time.perf_counter()
        for rid, name in self._db.execute("SELECT id, name FROM robots"):
            self._robot_ids[name], self._robot_names[rid] = rid, name
        batch: list[tuple] = []
        cur = self._db.execute(
            "SELECT id, robot, stamp, gist, bow_ids, bow_counts, processed "
            "FROM keyframes ORDER BY id"
        )
        pending = []
        for row in cur:
            batch.append(row)
            if not row[6]:
                pending.append(row[0])
            if len(batch) >= 10000:
                self._index_rows(batch)
                batch = []
        self._index_rows(batch)
        for kf in pending:
            self._queue.put(kf)
        log.info(
            "place index rebuilt: %d keyframes of %d robots in %.1f s (%d to process)",
            len(self.index),
            len(self._robot_ids),
            time.perf_counter() - t,
            len(pending),
        )

    def _index_rows(self, rows: list[tuple]) -> None:
        if not rows:
            return
        self.index.add_many(
            [r[0] for r in rows],
            [r[1] for r in rows],
            [r[2] for r in rows],
            np.stack([np.frombuffer(r[3], dtype="<f2") for r in rows]),
            [np.frombuffer(r[4], dtype="<u4") for r in rows],
            [np.frombuffer(r[5], dtype="<u2") for r in rows],
        )

    def _robot(self, name: str, create: bool) -> int:
        rid = self._robot_ids.get(name)
        if rid is None:
            if not create:
                raise UnknownRobot(f"Unknown robot {name!r}")
            cur = self._db.execute(
                "INSERT INTO robots (name, created) VALUES (?, ?)", (name, time.time())
            )
            rid = cur.lastrowid
            self._robot_ids[name], self._robot_names[rid] = rid, name
        return rid

    def add_keyframe(self, robot_id: str, data: bytes) -> tuple[int, bool]:
        """Store one encoded frame for robot_id; returns (keyframe id, newly created).

        Re-sending the identical frame is idempotent; a different frame at the same
        stamp is a Conflict. Returns only once the keyframe is durably committed.
        """
        return self.add_keyframes(robot_id, [data])[0]

    def _check(self, robot_id: str, data: bytes) -> Frame:
        frame = decode(data)
        if frame.robot_id != robot_id:
            raise BadInput(f"Frame is of robot {frame.robot_id!r}, posted for {robot_id!r}")
        if frame.vocab_id != self.vocabulary.vocab_id:
            raise BadInput(
                f"Frame BoW is over vocabulary {frame.vocab_id!r}, this database "
                f"uses {self.vocabulary.vocab_id!r}"
            )
        if len(frame.gist) != self.index.dim:
            raise BadInput(f"Expected a GIST of {self.index.dim} values, got {len(frame.gist)}")
        if len(frame.bow_ids) and int(frame.bow_ids.max()) >= self.vocabulary.n_words:
            raise BadInput(
                f"BoW word id {int(frame.bow_ids.max())} outside the "
                f"{self.vocabulary.n_words}-word vocabulary"
            )
        return frame

    def add_keyframes(self, robot_id: str, datas: list[bytes]) -> list[tuple[int, bool]]:
        """Store encoded frames of one robot durably; returns (id, created) for each.

        Group commit: concurrent callers queue their frames, and whoever holds the write
        lock commits everything queued in one transaction (one fsync for many robots).
        """
        check_robot_id(robot_id)
        items = [_Pending(robot_id, self._check(robot_id, d), bytes(d)) for d in datas]
        with self._pending_lock:
            self._pending.extend(items)
        with self._write_lock:
            if not items[-1].done:
                with self._pending_lock:
                    batch, self._pending = self._pending, []
                self._commit(batch)
        for it in items:
            if it.error is not None:
                raise it.error
        return [it.result for it in items]

    def _commit(self, batch: list[_Pending]) -> None:
        """Write a batch in one transaction (caller holds the write lock)."""
        if self._closed:
            for it in batch:
                it.error, it.done = Unavailable("place database is shutting down"), True
            return
        new_robots = [n for n in {it.robot_id for it in batch} if n not in self._robot_ids]
        added: list[_Pending] = []
        self._db.execute("BEGIN IMMEDIATE")
        try:
            for it in batch:
                rid = self._robot(it.robot_id, create=True)
                row = self._db.execute(
                    "SELECT id, data FROM keyframes WHERE robot=? AND stamp=?",
                    (rid, it.frame.stamp),
                ).fetchone()
                if row is None and any(
                    o.robot_id == it.robot_id and o.frame.stamp == it.frame.stamp for o in added
                ):
                    row = next(
                        (o.result[0], o.data)
                        for o in added
                        if o.robot_id == it.robot_id and o.frame.stamp == it.frame.stamp
                    )
                if row is not None:
                    if bytes(row[1]) == it.data:
                        it.result = (int(row[0]), False)
                    else:
                        it.error = Conflict(
                            f"Robot {it.robot_id!r} already has a different "
                            f"keyframe at stamp {it.frame.stamp}"
                        )
                    continue
                f = it.frame
                cur = self._db.execute(
                    "INSERT INTO keyframes (robot, stamp, created, gist, bow_ids, bow_counts, "
                    "data) VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        rid,
                        f.stamp,
                        time.time(),
                        f.gist.astype("<f2").tobytes(),
                        f.bow_ids.astype("<u4").tobytes(),
                        f.bow_counts.astype("<u2").tobytes(),
                        it.data,
                    ),
                )
                it.result = (int(cur.lastrowid), True)
                added.append(it)
            self._db.execute("COMMIT")
            if added:
                self._note_acknowledged(max(it.result[0] for it in added))
        except BaseException as exc:
            self._db.execute("ROLLBACK")
            for name in new_robots:
                if name in self._robot_ids:
                    self._robot_names.pop(self._robot_ids.pop(name), None)
            for it in batch:
                it.error, it.done = (
                    exc if isinstance(exc, Exception) else Unavailable("interrupted"),
                    True,
                )
            raise
        finally:
            for it in batch:
                it.done = True
        if added:
            self.index.add_many(
                [it.result[0] for it in added],
                [self._robot_ids[it.robot_id] for it in added],
                [it.frame.stamp for it in added],
                np.stack([it.frame.gist for it in added]),
                [it.frame.bow_ids for it in added],
                [it.frame.bow_counts for it in added],
            )
            for it in added:
                self._queue.put(it.result[0])
            self._maybe_retrain(len(added))

    def frame_bytes(self, kf_id: int) -> bytes:
        """The stored encoded frame of a keyframe."""
        row = (
            self._reader()
            .execute("SELECT data FROM keyframes WHERE id=?", (int(kf_id),))
            .fetchone()
        )
        if row is None:
            raise UnknownKeyframe(f"Unknown keyframe {kf_id}")
        data = bytes(row[0])
        if len(data) < 4 or zlib.crc32(memoryview(data)[:-4]) != int.from_bytes(
            data[-4:], "little"
        ):
            self.storage_errors += 1
            log.error("keyframe %d: stored frame fails its CRC-32 (storage corrupted)", kf_id)
            raise StorageCorrupt(
                f"Keyframe {kf_id}: the stored frame fails its checksum (storage corrupted); "
                "the operator should restore it or delete the robot"
            )
        return data

    def load_frame(self, kf_id: int) -> Frame:
        """The full stored frame of a keyframe (local features included)."""
        return decode(self.frame_bytes(kf_id))

    def keyframe_info(self, kf_id: int) -> dict:
        row = (
            self._reader()
            .execute(
                "SELECT k.id, r.name, k.stamp, k.processed, length(k.data) FROM keyframes k "
                "JOIN robots r ON r.id = k.robot WHERE k.id=?",
                (int(kf_id),),
            )
            .fetchone()
        )
        if row is None:
            raise UnknownKeyframe(f"Unknown keyframe {kf_id}")
        return {
            "id": row[0],
            "robot_id": row[1],
            "stamp": row[2],
            "processed": bool(row[3]),
            "bytes": row[4],
        }

    # --- queries --------------------------------------------------------------------

    def robot_name(self, rid: int) -> str | None:
        """The robot's name; None once it has been deleted (a query may race a delete)."""
        return self._robot_names.get(rid)

    def robots(self) -> list[dict]:
        rows = (
            self._reader()
            .execute(
                "SELECT r.name, count(k.id), min(k.stamp), max(k.stamp) FROM robots r "
                "LEFT JOIN keyframes k ON k.robot = r.id GROUP BY r.id ORDER BY r.name"
            )
            .fetchall()
        )
        return [
            {"robot_id": n, "keyframes": c, "first_stamp": a, "last_stamp": b}
            for n, c, a, b in rows
        ]

    def keyframes(self, robot_id: str, offset: int = 0, limit: int = 1000) -> list[dict]:
        rid = self._robot(robot_id, create=False)
        rows = (
            self._reader()
            .execute(
                "SELECT id, stamp, processed FROM keyframes WHERE robot=? ORDER BY stamp "
                "LIMIT ? OFFSET ?",
                (rid, int(limit), int(offset)),
            )
            .fetchall()
        )
        return [{"id": i, "stamp": s, "processed": bool(p)} for i, s, p in rows]

    def make_filter(
        self,
        robot: str | None = None,
        exclude_robot: str | None = None,
        max_stamp: float | None = None,
    ) -> Filter:
        return Filter(
            robots=None if robot is None else {self._robot(robot, create=False)},
            exclude_robots=set()
            if exclude_robot is None or exclude_robot not in self._robot_ids
            else {self._robot_ids[exclude_robot]},
            max_stamp=max_stamp,
        )

    def query(self, frame: Frame, flt: Filter | None = None) -> CascadeResult:
        """The cascade's answer for one frame against the stored keyframes."""
        if frame.vocab_id != self.vocabulary.vocab_id:
            raise BadInput(
                f"Frame BoW is over vocabulary {frame.vocab_id!r}, this database "
                f"uses {self.vocabulary.vocab_id!r}"
            )
        return run_cascade(frame, self.index, self.load_frame, self.params, flt)

    def overlaps(self, robot_a: str, robot_b: str) -> list[Overlap]:
        """Verified keyframe pairs between two robots, oriented a -> b, by stamp of a."""
        ra, rb = self._robot(robot_a, create=False), self._robot(robot_b, create=False)
        rows = (
            self._reader()
            .execute(
                "SELECT o.kf_a, ka.stamp, o.kf_b, kb.stamp, o.inliers, o.matches, o.robot_a, "
                "o.source "
                "FROM overlaps o JOIN keyframes ka ON ka.id=o.kf_a "
                "JOIN keyframes kb ON kb.id=o.kf_b "
                "WHERE (o.robot_a=? AND o.robot_b=?) OR (o.robot_a=? AND o.robot_b=?)",
                (ra, rb, rb, ra),
            )
            .fetchall()
        )
        out = []
        for ka, sa, kb, sb, inl, m, first, src in rows:
            if first != ra:
                ka, sa, kb, sb = kb, sb, ka, sa
            out.append(Overlap(robot_a, ka, sa, robot_b, kb, sb, inl, m, src))
        return sorted(out, key=lambda o: (o.stamp_a, o.stamp_b))

    def overlap_graph(self) -> list[dict]:
        """Every robot pair with verified overlaps: count, best and total inliers."""
        rows = (
            self._reader()
            .execute(
                "SELECT robot_a, robot_b, count(*), max(inliers), sum(inliers) FROM overlaps "
                "GROUP BY robot_a, robot_b"
            )
            .fetchall()
        )
        merged: dict[tuple[str, str], list[int]] = {}
        for ra, rb, n, best, total in rows:
            a, b = sorted((self._robot_names[ra], self._robot_names[rb]))
            acc = merged.setdefault((a, b), [0, 0, 0])
            acc[0] += n
            acc[1] = max(acc[1], best)
            acc[2] += total
        return [
            {"robot_a": a, "robot_b": b, "pairs": n, "best_inliers": best, "total_inliers": total}
            for (a, b), (n, best, total) in sorted(merged.items())
        ]

    def pending(self) -> int:
        """Keyframes still waiting for overlap detection."""
        return self._queue.unfinished_tasks

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every queued keyframe is processed; False on timeout."""
        end = time.monotonic() + timeout
        while self._queue.unfinished_tasks:
            if time.monotonic() > end:
                return False
            time.sleep(0.02)
        return True

    def ping(self) -> bool:
        """The database answers a trivial read."""
        try:
            return self._reader().execute("SELECT 1").fetchone() == (1,)
        except sqlite3.Error:
            return False

    def stats(self) -> dict:
        sizes = self.index.cluster_sizes()
        nonempty = sizes[sizes > 0]
        return {
            "keyframes": len(self.index),
            "robots": len(self._robot_ids),
            "pending": self.pending(),
            "clusters": int(len(sizes)),
            "cluster_mean": float(sizes.mean()) if len(sizes) else 0.0,
            "cluster_max": int(sizes.max()) if len(sizes) else 0,
            "nonempty_clusters": int(len(nonempty)),
            "overlaps": self._reader().execute("SELECT count(*) FROM overlaps").fetchone()[0],
            "vocab_id": self.vocabulary.vocab_id,
            "db_path": str(self.path),
            "db_bytes": self.path.stat().st_size if self.path.exists() else 0,
            "storage_errors": self.storage_errors,
            "worker_failures": self.failures,
            "parked": dict(self.parked),
            "startup_warning": self.startup_warning,
        }

    # --- administration --------------------------------------------------------------

    def delete_robot(self, robot_id: str) -> int:
        """Delete a robot, its keyframes and its overlaps; returns keyframes removed."""
        with self._write_lock:
            rid = self._robot(robot_id, create=False)
            ids = np.array(
                [r[0] for r in self._db.execute("SELECT id FROM keyframes WHERE robot=?", (rid,))],
                dtype=np.int64,
            )
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute("DELETE FROM overlaps WHERE robot_a=? OR robot_b=?", (rid, rid))
                self._db.execute("DELETE FROM links WHERE robot_a=? OR robot_b=?", (rid, rid))
                self._db.execute("DELETE FROM keyframes WHERE robot=?", (rid,))
                self._db.execute("DELETE FROM robots WHERE id=?", (rid,))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self.index.remove(ids)
            del self._robot_ids[robot_id]
            del self._robot_names[rid]
        return len(ids)

    def retrain(self, n_clusters: int | None = None) -> dict:
        """k-means the coarse codebook anew from the stored GISTs and swap the index in;
        queries and ingest go on meanwhile (thesis Fig. 2.12: uneven clusters)."""
        if not self._retraining.acquire(blocking=False):
            raise Conflict("A retraining is already running")
        try:
            t = time.perf_counter()
            k = n_clusters or self.retrain_policy.target_clusters(len(self.index))
            sizes = self.index.retrain(k)
            book = self.index.codebook.astype(np.float32)
            with self._write_lock:
                self._db.execute(
                    "INSERT INTO codebooks (created, n_clusters, dim, centroids) "
                    "VALUES (?, ?, ?, ?)",
                    (time.time(), len(book), book.shape[1], book.tobytes()),
                )
            info = {
                "clusters": int(len(sizes)),
                "keyframes": int(sizes.sum()),
                "cluster_max": int(sizes.max()),
                "cluster_mean": float(sizes.mean()),
                "seconds": time.perf_counter() - t,
            }
            log.info("codebook retrained: %s", info)
            return info
        finally:
            self._retraining.release()

    def needs_retrain(self) -> bool:
        p, n = self.retrain_policy, len(self.index)
        if not p.enabled or n < p.min_keyframes:
            return False
        sizes = self.index.cluster_sizes()
        mean = max(float(sizes.mean()), 1e-9)
        return mean > p.max_mean_list or sizes.max() > p.max_imbalance * mean

    def _maybe_retrain(self, added: int = 1) -> None:
        n = len(self.index)
        if n % 500 >= added or self._retraining.locked():
            return  # check every 500 keyframes
        if self.needs_retrain():
            threading.Thread(target=self._retrain_quietly, daemon=True).start()

    def _retrain_quietly(self) -> None:
        try:
            self.retrain()
        except Conflict:
            pass
        except Exception:
            log.exception("background codebook retraining failed")

    # --- links: map alignments registered by the aligner --------------------------------

    LINK_MIN_POINTS = 15
    LINK_MIN_SHARE = 0.15

    def add_link(self, robot_a: str, robot_b: str, T_a_b: np.ndarray) -> int:
        """Register a map alignment (B's map frame into A's, from a gated aligner result)
        and record, as overlaps with source "link", each keyframe's most co-visible
        keyframe of the other robot under it. Wide baselines defeat keyframe-level visual
        verification (SUN3D: even under the true transform, 2 of 13 keyframes share 4
        matching features) where the whole-map alignment succeeds; with it the overlap
        graph covers what the robots really share. Replaces the pair's earlier link.
        Returns the number of link overlaps recorded."""
        T = check_transform(T_a_b, "A link's transform")
        if robot_a == robot_b:
            raise BadInput("A link joins two different robots")
        ra, rb = self._robot(robot_a, create=False), self._robot(robot_b, create=False)
        if ra > rb:  # one row per robot pair
            ra, rb, T = rb, ra, np.linalg.inv(T)
        fa, fb = self._robot_frames(ra), self._robot_frames(rb)
        rows = _link_rows(fb, rb, fa, ra, T) + _link_rows(fa, ra, fb, rb, np.linalg.inv(T))
        now = time.time()
        with self._write_lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute(
                    "INSERT OR REPLACE INTO links VALUES (?, ?, ?, ?)",
                    (ra, rb, T.astype("<f8").tobytes(), now),
                )
                self._db.execute(
                    "DELETE FROM overlaps WHERE source='link' AND "
                    "((robot_a=? AND robot_b=?) OR (robot_a=? AND robot_b=?))",
                    (ra, rb, rb, ra),
                )
                n = self._insert_link_rows(rows, now)
                self._db.execute("COMMIT")
            except sqlite3.IntegrityError as exc:  # a robot deleted while the link was made
                self._db.execute("ROLLBACK")
                raise Conflict(
                    f"{robot_a} or {robot_b} was deleted while the link was registered"
                ) from exc
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        log.info("link %s-%s registered: %d co-visible keyframe pairs", robot_a, robot_b, n)
        return n

    def _insert_link_rows(self, rows, now: float) -> int:
        n = 0
        for kx, rx, ky, ry, seen, total in rows:
            hit = self._db.execute(
                "SELECT 1 FROM overlaps WHERE (kf_a=? AND kf_b=?) OR (kf_a=? AND kf_b=?)",
                (kx, ky, ky, kx),
            ).fetchone()
            if hit is None:
                self._db.execute(
                    "INSERT INTO overlaps VALUES (?, ?, ?, ?, ?, ?, ?, 'link')",
                    (kx, ky, rx, ry, seen, total, now),
                )
                n += 1
        return n

    def links(self) -> list[dict]:
        """Registered map alignments: {robot_a, robot_b, transform (B into A), created}."""
        rows = self._reader().execute("SELECT robot_a, robot_b, transform, created FROM links")
        return [
            {
                "robot_a": self._robot_names[a],
                "robot_b": self._robot_names[b],
                "transform": np.frombuffer(t, "<f8").reshape(4, 4).tolist(),
                "created": c,
            }
            for a, b, t, c in rows
        ]

    def _robot_kf_ids(self, rid: int) -> list[int]:
        rows = self._reader().execute(
            "SELECT id FROM keyframes WHERE robot=? ORDER BY stamp", (rid,)
        )
        return [r[0] for r in rows]

    def _robot_frames(self, rid: int) -> list[tuple[int, Frame]]:
        return [(i, self.load_frame(i)) for i in self._robot_kf_ids(rid)]

    def _link_overlaps_for(self, kf_id: int, frame: Frame, rid: int) -> list[tuple]:
        """Link overlaps of one new keyframe with the robots it is linked to."""
        rows = []
        for a, b, t in (
            self._reader()
            .execute(
                "SELECT robot_a, robot_b, transform FROM links WHERE robot_a=? OR robot_b=?",
                (rid, rid),
            )
            .fetchall()
        ):
            T = np.frombuffer(t, "<f8").reshape(4, 4)
            other, T_other_this = (a, T) if b == rid else (b, np.linalg.inv(T))
            # only the other robot's keyframes near this one are read from disk: their
            # point centres are cached (24 bytes each) after the first look
            ids = self._robot_kf_ids(other)
            for i in ids:
                if i not in self._centres:
                    self._centres[i] = _centre(self.load_frame(i))
            c = T_other_this[:3, :3] @ _centre(frame) + T_other_this[:3, 3]
            near = [i for i in ids if np.linalg.norm(self._centres[i] - c) < LINK_NEAR_M]
            ys = [(i, self.load_frame(i)) for i in near]
            rows += _link_rows([(kf_id, frame)], rid, ys, other, T_other_this)
        return rows

    # --- overlap worker ---------------------------------------------------------------

    def process(self, kf_id: int) -> list[Overlap]:
        """Find and record this keyframe's verified winner in each other robot."""
        try:
            frame = self.load_frame(kf_id)
        except UnknownKeyframe:
            return []  # deleted meanwhile
        rid = self._robot_ids.get(frame.robot_id)
        if rid is None:
            return []
        result = run_cascade(
            frame, self.index, self.load_frame, self.params, Filter(exclude_robots={rid})
        )
        best: dict[int, object] = {}
        for c in result.verified:
            if c.robot not in best:
                best[c.robot] = c
        link_rows = self._link_overlaps_for(kf_id, frame, rid)
        now = time.time()
        with self._write_lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                for c in best.values():
                    self._db.execute(
                        "INSERT OR REPLACE INTO overlaps "
                        "(kf_a, kf_b, robot_a, robot_b, inliers, matches, created) "
                        "VALUES (?, ?, ?, ?, ?, ?, ?)",
                        (
                            kf_id,
                            c.kf_id,
                            rid,
                            c.robot,
                            c.verification.inliers,
                            c.verification.matches,
                            now,
                        ),
                    )
                self._insert_link_rows(link_rows, now)
                self._db.execute("UPDATE keyframes SET processed=1 WHERE id=?", (kf_id,))
                self._db.execute("COMMIT")
            except sqlite3.IntegrityError:
                self._db.execute("ROLLBACK")  # a keyframe was deleted meanwhile
                return []
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return [
            Overlap(
                frame.robot_id,
                kf_id,
                frame.stamp,
                self._robot_names.get(c.robot, "?"),
                c.kf_id,
                c.stamp,
                c.verification.inliers,
                c.verification.matches,
            )
            for c in best.values()
        ]

    def _work(self) -> None:
        while True:
            kf = self._queue.get()
            try:
                # stopping: what is left stays unprocessed, re-queued at the next start
                if kf is not None and not self._stopping:
                    self.process(kf)
            except Exception as exc:  # one keyframe's failure blocks none of the others
                self._park(kf, exc)
            finally:
                self._queue.task_done()
            if kf is None:
                return

    def _park(self, kf: int, exc: Exception) -> None:
        """Count a keyframe whose overlap detection failed and keep its reason (the last
        100); it stays unprocessed in storage, so the next start tries it again."""
        log.exception("overlap detection failed for keyframe %s", kf)
        self.failures += 1
        self.parked[kf] = f"{type(exc).__name__}: {exc}"[:300]
        while len(self.parked) > 100:
            self.parked.pop(next(iter(self.parked)))

    def process_pending(self) -> None:
        """Synchronously process queued keyframes (for use without the background worker)."""
        while True:
            try:
                kf = self._queue.get_nowait()
            except queue.Empty:
                return
            try:
                if kf is not None:
                    self.process(kf)
            except Exception as exc:
                self._park(kf, exc)
            finally:
                self._queue.task_done()

    def close(self, drain_timeout: float = 10.0) -> None:
        """Finish in-flight writes, let the worker finish the keyframe it is on (at most
        `drain_timeout` in all; unprocessed keyframes are re-queued at the next start),
        checkpoint the write-ahead log into the database and close it."""
        with self._write_lock:
            self._closed = True
        if self._worker is not None:
            self._stopping = True
            self._queue.put(None)
            self._worker.join(timeout=drain_timeout)
        with self._write_lock:
            try:
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                Path(str(self.path) + ".open").unlink(missing_ok=True)
            except (sqlite3.Error, OSError):
                log.exception("closing %s", self.path)
            self._db.close()


def _link_rows(xs, rx: int, ys, ry: int, T_y_x: np.ndarray) -> list[tuple]:
    """For each keyframe x (id, frame) of robot rx, its most co-visible keyframe of robot ry
    under T_y_x (rx's map into ry's): rows (kf_x, rx, kf_y, ry, points seen, points)."""
    out = []
    cy = np.array([_centre(fy) for _, fy in ys]).reshape(-1, 3)
    for kx, fx in xs:
        best = None
        c = T_y_x[:3, :3] @ _centre(fx) + T_y_x[:3, 3]
        near = np.flatnonzero(np.linalg.norm(cy - c, axis=1) < LINK_NEAR_M)
        for k in near:
            ky, fy = ys[k]
            seen, share = sparse_covisibility(fy, fx, T_y_x)
            ok = seen >= PlaceDB.LINK_MIN_POINTS and share >= PlaceDB.LINK_MIN_SHARE
            if ok and (best is None or seen > best[4]):
                n_pts = int(fx.point_valid.sum()) if fx.point_valid is not None else 0
                best = (kx, rx, ky, ry, seen, n_pts)
        if best is not None:
            out.append(best)
    return out


LINK_NEAR_M = 4.0  # keyframes whose seen points' centres are farther apart share nothing


def _centre(f: Frame) -> np.ndarray:
    if f.points is None or f.point_valid is None or not f.point_valid.any():
        return np.full(3, np.inf)
    return f.points[f.point_valid].astype(np.float64).mean(0)


def check_database_file(path: Path) -> None:
    """A quick integrity check of an existing database file, before a service starts on it:
    StorageCorrupt with the reason (a damaged or foreign file), never a traceback."""
    path = Path(path)
    if not path.exists():
        return
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            result = con.execute("PRAGMA quick_check").fetchone()[0]
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        result = str(exc)
    if result != "ok":
        raise StorageCorrupt(
            f"{path} is damaged or not a place database ({result}): restore it from a backup "
            "or move it away to start an empty one"
        )
