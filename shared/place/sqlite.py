"""The place database's embedded storage: SQLite in WAL mode (`Store` of `fleetmap.place.store`).

A keyframe is acknowledged only after its transaction is committed with
`synchronous=FULL`, so an acknowledged keyframe survives a crash of the process or the
machine. Files beside the database: `DB.acked` (the newest acknowledged keyframe id) and
`DB.open` (present while a process has it open) tell a database that lost its write-ahead
log from one that did not.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

import fleetmap.place.sqlite_files as files
from fleetmap.errors import Conflict, Unavailable, UnknownKeyframe
from fleetmap.place.store import (
    GroupCommit,
    IndexRows,
    LinkRow,
    OverlapRow,
    Pending,
    WinnerRow,
    checked_frame,
)

log = logging.getLogger(__name__)


class SQLiteStore(GroupCommit):
    """Robots, keyframes, overlaps, links and codebooks in one SQLite file."""

    shared = False  # one process has the file open (`sqlite_files`' open marker tells)

    def __init__(self, path: str | Path, vocab_id: str):
        self.path = Path(path)
        self.where = str(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._held = files.hold(self.path)  # one process a database
        lost_log = files.log_was_lost(self.path)  # before SQLite opens it (a new log)
        self.vocab_id = vocab_id
        self.storage_errors = 0
        self._init_group_commit()
        self._local = threading.local()
        self._db = files.connect(self.path)
        with self._write_lock:
            files.init_schema(self._db, self.path, vocab_id)
            self.startup_warning = files.open_checks(self._db, self.path, lost_log)
        self._codes: dict[str, int] = {}
        self._names: dict[int, str] = {}
        for code, name in self._db.execute("SELECT id, name FROM robots"):
            self._codes[name], self._names[code] = code, name

    def robot_code(self, name: str) -> int | None:
        return self._codes.get(name)

    def robot_name(self, code: int) -> str | None:
        """The robot's name; None once it has been deleted (a query may race a delete)."""
        return self._names.get(code)

    def robot_count(self) -> int:
        return len(self._codes)

    def _create_robot(self, name: str) -> int:
        code = self._codes.get(name)
        if code is None:
            cur = self._db.execute(
                "INSERT INTO robots (name, created) VALUES (?, ?)", (name, time.time())
            )
            code = cur.lastrowid
            self._codes[name], self._names[code] = code, name
        return code

    def codebook(self) -> np.ndarray | None:
        row = self._db.execute(
            "SELECT n_clusters, dim, centroids FROM codebooks ORDER BY id DESC LIMIT 1"
        ).fetchone()
        if row is None:
            return None
        return np.frombuffer(row[2], dtype=np.float32).reshape(row[0], row[1])

    @contextlib.contextmanager
    def exclusive(self, what: str):
        """This process is the file's only one: always held (`Store.exclusive`)."""
        yield lambda: True

    def save_codebook(self, centroids: np.ndarray) -> None:
        book = np.ascontiguousarray(centroids, np.float32)
        with self._write_lock:
            self._db.execute(
                "INSERT INTO codebooks (created, n_clusters, dim, centroids) VALUES (?, ?, ?, ?)",
                (time.time(), len(book), book.shape[1], book.tobytes()),
            )

    # --- keyframes ----------------------------------------------------------------

    def index_rows(self, batch: int = 10000) -> Iterator[IndexRows]:
        """Every stored keyframe's summary columns, in id order, in batches."""
        cur = self._db.execute(
            "SELECT id, robot, stamp, gist, bow_ids, bow_counts, processed "
            "FROM keyframes ORDER BY id"
        )
        while rows := cur.fetchmany(batch):
            yield IndexRows.from_rows(rows)

    def _commit(self, batch: list[Pending]) -> list[Pending]:
        """Write a batch in one transaction (caller holds the write lock)."""
        if self._refused_when_closed(batch):
            return []
        new_robots = [n for n in {it.robot_id for it in batch} if n not in self._codes]
        added: dict[tuple[str, float], Pending] = {}
        self._db.execute("BEGIN IMMEDIATE")
        try:
            for it in batch:
                self._insert(it, added)
            self._db.execute("COMMIT")
            if added:
                files.note_acknowledged(self.path, max(it.result[0] for it in added.values()))
        except BaseException as exc:
            self._db.execute("ROLLBACK")
            for name in new_robots:
                if name in self._codes:
                    self._names.pop(self._codes.pop(name), None)
            for it in batch:
                it.error = exc if isinstance(exc, Exception) else Unavailable("interrupted")
            raise
        finally:
            for it in batch:
                it.done = True
        return list(added.values())

    def _insert(self, it: Pending, added: dict[tuple[str, float], Pending]) -> None:
        """One frame of a batch: stored, found identical (idempotent), or a Conflict."""
        code, f = self._create_robot(it.robot_id), it.frame
        row = self._db.execute(
            "SELECT id, data FROM keyframes WHERE robot=? AND stamp=?", (code, f.stamp)
        ).fetchone()
        same_batch = added.get((it.robot_id, f.stamp))
        if row is None and same_batch is not None:
            row = (same_batch.result[0], same_batch.data)
        if row is not None:
            if bytes(row[1]) == it.data:
                it.result = (int(row[0]), False)
                self._insert_view(it, "INSERT OR IGNORE")
            else:
                it.error = Conflict(
                    f"Robot {it.robot_id!r} already has a different keyframe at stamp {f.stamp}"
                )
            return
        cur = self._db.execute(
            "INSERT INTO keyframes (robot, stamp, created, gist, bow_ids, bow_counts, data) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (
                code,
                f.stamp,
                time.time(),
                f.gist.astype("<f2").tobytes(),
                f.bow_ids.astype("<u4").tobytes(),
                f.bow_counts.astype("<u2").tobytes(),
                it.data,
            ),
        )
        it.result = (int(cur.lastrowid), True)
        added[(it.robot_id, f.stamp)] = it
        self._insert_view(it, "INSERT")

    def _insert_view(self, it: Pending, verb: str) -> None:
        if it.view is not None:
            self._db.execute(f"{verb} INTO views VALUES (?, ?, ?)", (it.result[0], *it.view))

    def view_bytes(self, kf_id: int) -> tuple[bytes, bytes] | None:
        """A keyframe's stored (colour, depth) images; None if posted without them."""
        row = self._read("SELECT rgb, depth FROM views WHERE kf=?", (int(kf_id),)).fetchone()
        return None if row is None else (bytes(row[0]), bytes(row[1]))

    def view_ids(self, code: int) -> list[int]:
        """The robot's keyframes stored with a view, in time order."""
        sql = "SELECT k.id FROM keyframes k JOIN views v ON v.kf = k.id WHERE k.robot=? "
        return [r[0] for r in self._read(sql + "ORDER BY k.stamp", (code,))]

    def live_get(self, key: str) -> str | None:
        row = self._read("SELECT value FROM live WHERE key=?", (key,)).fetchone()
        return None if row is None else row[0]

    def live_put(self, key: str, value: str) -> None:
        with self._write_lock:
            self._db.execute("INSERT OR REPLACE INTO live VALUES (?, ?)", (key, value))

    def live_cas(self, key: str, old: str | None, new: str) -> bool:
        with self._write_lock:
            return files.live_cas(self._db, key, old, new)

    def frame_bytes(self, kf_id: int) -> bytes:
        """The stored encoded frame of a keyframe, its CRC-32 checked."""
        row = self._read("SELECT data FROM keyframes WHERE id=?", (int(kf_id),)).fetchone()
        return checked_frame(self, kf_id, row)

    def keyframe_info(self, kf_id: int) -> dict:
        row = self._read(
            "SELECT k.id, r.name, k.stamp, k.processed, length(k.data) FROM keyframes k "
            "JOIN robots r ON r.id = k.robot WHERE k.id=?",
            (int(kf_id),),
        ).fetchone()
        if row is None:
            raise UnknownKeyframe(f"Unknown keyframe {kf_id}")
        keys = ("id", "robot_id", "stamp", "processed", "bytes")
        info = dict(zip(keys, row, strict=True))
        info["processed"] = bool(info["processed"])
        return info

    def robots(self) -> list[dict]:
        rows = self._read(
            "SELECT r.name, count(k.id), min(k.stamp), max(k.stamp) FROM robots r "
            "LEFT JOIN keyframes k ON k.robot = r.id GROUP BY r.id ORDER BY r.name"
        ).fetchall()
        return [
            {"robot_id": n, "keyframes": c, "first_stamp": a, "last_stamp": b}
            for n, c, a, b in rows
        ]

    def keyframes(self, code: int, offset: int, limit: int) -> list[dict]:
        rows = self._read(
            "SELECT id, stamp, processed FROM keyframes WHERE robot=? ORDER BY stamp "
            "LIMIT ? OFFSET ?",
            (code, int(limit), int(offset)),
        ).fetchall()
        return [{"id": i, "stamp": s, "processed": bool(p)} for i, s, p in rows]

    def robot_keyframe_ids(self, code: int) -> list[int]:
        rows = self._read("SELECT id FROM keyframes WHERE robot=? ORDER BY stamp", (code,))
        return [r[0] for r in rows]

    # --- overlaps and links ----------------------------------------------------------

    def overlap_rows(self, code_a: int, code_b: int) -> list[OverlapRow]:
        rows = self._read(
            "SELECT o.kf_a, ka.stamp, o.robot_a, o.kf_b, kb.stamp, o.robot_b, o.inliers, "
            "o.matches, o.source FROM overlaps o JOIN keyframes ka ON ka.id=o.kf_a "
            "JOIN keyframes kb ON kb.id=o.kf_b "
            "WHERE (o.robot_a=? AND o.robot_b=?) OR (o.robot_a=? AND o.robot_b=?)",
            (code_a, code_b, code_b, code_a),
        ).fetchall()
        return [OverlapRow(*r) for r in rows]

    def overlap_counts(self) -> list[tuple[int, int, int, int, int]]:
        """(robot_a, robot_b, pairs, best inliers, total inliers) per stored orientation."""
        return self._read(
            "SELECT robot_a, robot_b, count(*), max(inliers), sum(inliers) FROM overlaps "
            "GROUP BY robot_a, robot_b"
        ).fetchall()

    def overlap_total(self) -> int:
        return self._read("SELECT count(*) FROM overlaps").fetchone()[0]

    def record_overlaps(
        self, kf_id: int, code: int, winners: list[WinnerRow], links: list[LinkRow]
    ) -> bool:
        """Store one keyframe's verified winners and link overlaps and mark it processed;
        False when a keyframe involved was deleted meanwhile (nothing stored)."""
        now = time.time()
        with self._write_lock, files.Transaction(self._db) as tx:
            try:
                for kf_b, code_b, inliers, matches in winners:
                    self._db.execute(
                        "INSERT OR REPLACE INTO overlaps "
                        "(kf_a, kf_b, robot_a, robot_b, inliers, matches, created) "
                        "VALUES (?, ?, ?, ?, ?, ?, ?)",
                        (kf_id, kf_b, code, code_b, inliers, matches, now),
                    )
                self._insert_link_rows(links, now)
                self._db.execute("UPDATE keyframes SET processed=1 WHERE id=?", (kf_id,))
            except sqlite3.IntegrityError:
                raise files.Rollback() from None
        return not tx.rolled_back

    def put_link(self, code_a: int, code_b: int, T_a_b: np.ndarray, rows: list[LinkRow]) -> int:
        """Store the link (replacing the pair's earlier one and its link overlaps) and the
        link overlaps not already known; returns how many were added."""
        now = time.time()
        with self._write_lock, files.Transaction(self._db) as tx:
            try:
                self._db.execute(
                    "INSERT OR REPLACE INTO links VALUES (?, ?, ?, ?)",
                    (code_a, code_b, np.asarray(T_a_b, "<f8").tobytes(), now),
                )
                self._db.execute(
                    "DELETE FROM overlaps WHERE source='link' AND "
                    "((robot_a=? AND robot_b=?) OR (robot_a=? AND robot_b=?))",
                    (code_a, code_b, code_b, code_a),
                )
                n = self._insert_link_rows(rows, now)
            except sqlite3.IntegrityError:  # a robot deleted while the link was made
                raise files.Rollback() from None
        if tx.rolled_back:
            raise Conflict("A robot was deleted while the link was registered")
        return n

    def _insert_link_rows(self, rows: list[LinkRow], now: float) -> int:
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

    def links(self, code: int | None = None) -> list[tuple[int, int, np.ndarray, float]]:
        """(robot_a, robot_b, T_a_b, created) of every link, or of those of one robot."""
        sql = "SELECT robot_a, robot_b, transform, created FROM links"
        rows = (
            self._read(sql)
            if code is None
            else self._read(sql + " WHERE robot_a=? OR robot_b=?", (code, code))
        )
        return [(a, b, np.frombuffer(t, "<f8").reshape(4, 4), c) for a, b, t, c in rows]

    # --- administration ----------------------------------------------------------------

    def delete_robot(self, code: int, then: Callable[[np.ndarray], None]) -> int:
        """Delete a robot, its keyframes, overlaps, links and the live map's pair states
        and placements derived from it, in one transaction; `then(ids)` runs under the
        write lock after the commit. Returns the number of keyframes removed."""
        with self._write_lock:
            ids = np.array(
                [r[0] for r in self._db.execute("SELECT id FROM keyframes WHERE robot=?", (code,))],
                dtype=np.int64,
            )
            with files.Transaction(self._db):
                self._db.execute("DELETE FROM overlaps WHERE robot_a=? OR robot_b=?", (code, code))
                self._db.execute("DELETE FROM links WHERE robot_a=? OR robot_b=?", (code, code))
                self._db.execute("DELETE FROM keyframes WHERE robot=?", (code,))
                self._db.execute("DELETE FROM robots WHERE id=?", (code,))
                files.forget_live(self._db, self._names[code])
            then(ids)
            self._codes.pop(self._names.pop(code), None)
        return len(ids)

    def ping(self) -> bool:
        """The database answers a trivial read."""
        try:
            return self._read("SELECT 1").fetchone() == (1,)
        except sqlite3.Error:
            return False

    def size_bytes(self) -> int:
        return self.path.stat().st_size if self.path.exists() else 0

    def refuse_writes(self) -> None:
        """From now on writes answer Unavailable (shutting down); in-flight ones finish."""
        with self._write_lock:
            self._closed = True

    def close(self) -> None:
        """Refuse further writes, checkpoint the write-ahead log into the database, close."""
        with self._write_lock:
            self._closed = True
            files.close_cleanly(self._db, self.path)
            self._held.close()

    def _read(self, sql: str, args: tuple = ()) -> sqlite3.Cursor:
        """A read on this thread's own connection: WAL readers never block the writer."""
        if not hasattr(self._local, "conn"):
            self._local.conn = files.connect(self.path)
        return self._local.conn.execute(sql, args)
