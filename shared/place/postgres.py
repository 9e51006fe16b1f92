"""The place database on PostgreSQL (`Store` of `fleetmap.place.store`), for any number of
service replicas over one database.

- Keyframe ids follow commit order: each group commit takes a transaction-level advisory
  lock before allocating ids, so a replica that has read every id up to N has read every
  keyframe committed before N; the others' keyframes reach its index by catch-up on id
  (`PlaceDB.catch_up`, every 0.1 s and after each of its own commits).
- Overlap detection is a queue in the table itself: a replica claims the oldest unprocessed
  keyframe with `FOR NO KEY UPDATE SKIP LOCKED` and records its overlaps in the same
  transaction (not FOR UPDATE: that lock blocks the other replicas' overlap rows that
  reference the keyframe, and two claims deadlock); a replica killed mid-keyframe drops
  its connection, so the claim returns to the queue.
  A keyframe whose detection raises three times is left aside (counted as parked).
- Schema creation, link registration and codebook retraining each run under their own
  advisory lock, so two replicas never do them at once.
- PostgreSQL unreachable: every call raises Unavailable (HTTP 503) naming the server; the
  pool reconnects by itself once it is back.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator

import numpy as np

from fleetmap.errors import Conflict, Unavailable, UnknownKeyframe
from fleetmap.place import postgres_schema as schema
from fleetmap.place.store import (
    PG_TIMEOUT_S,
    GroupCommit,
    IndexRows,
    LinkRow,
    OverlapRow,
    Pending,
    WinnerRow,
    checked_frame,
)

log = logging.getLogger(__name__)

MAX_ATTEMPTS = 3  # a keyframe whose overlap detection raised this often is left aside


class PostgresStore(GroupCommit):
    """Robots, keyframes, overlaps, links and codebooks in one PostgreSQL database."""

    shared = True  # other processes write the same database

    def __init__(
        self, url: str, vocab_id: str, pool_size: int = 8, timeout_s: float = PG_TIMEOUT_S
    ):
        from psycopg_pool import ConnectionPool

        self.url, self.where = url, schema.redacted(url)
        self.path = None
        self.vocab_id, self.timeout_s = vocab_id, timeout_s
        self.storage_errors = 0
        self.startup_warning = ""
        self._init_group_commit()
        self._codes: dict[str, int] = {}
        self._names: dict[int, str] = {}
        self.pool = ConnectionPool(
            url,
            min_size=1,
            max_size=pool_size,
            kwargs={"autocommit": True, "connect_timeout": 5},
            check=ConnectionPool.check_connection,
            open=False,
            name="fleetmap-place-db",
        )
        schema.check_reachable(url)  # one clear line, not a pool timeout, when it is down
        try:
            self.pool.open(wait=True, timeout=30)
        except Exception as exc:
            raise Unavailable(f"PostgreSQL at {self.where} is unreachable: {exc}") from exc
        with self.conn() as con:
            schema.create(con, vocab_id, self.where)

    @contextlib.contextmanager
    def conn(self):
        """A pooled connection (autocommit); PostgreSQL unreachable -> Unavailable."""
        import psycopg
        from psycopg_pool import PoolTimeout

        try:
            with self.pool.connection(timeout=self.timeout_s) as con:
                yield con
        except (psycopg.OperationalError, PoolTimeout) as exc:
            raise Unavailable(
                f"PostgreSQL at {self.where} is unreachable: {str(exc).strip()[:300]}",
                retry_after=2,
            ) from exc

    def _one(self, sql: str, args: tuple = ()):
        with self.conn() as con:
            return con.execute(sql, args).fetchone()

    def _all(self, sql: str, args: tuple = ()) -> list:
        with self.conn() as con:
            return con.execute(sql, args).fetchall()

    # --- robots and codebooks -----------------------------------------------------

    def robot_code(self, name: str) -> int | None:
        code = self._codes.get(name)
        if code is None:
            row = self._one("SELECT id FROM robots WHERE name=%s", (name,))
            if row is not None:
                code = self._codes[name] = row[0]
                self._names[code] = name
        return code

    def robot_name(self, code: int) -> str | None:
        name = self._names.get(code)
        if name is None:
            row = self._one("SELECT name FROM robots WHERE id=%s", (code,))
            if row is not None:
                name = self._names[code] = row[0]
                self._codes[name] = code
        return name

    def forget_robot(self, code: int) -> None:
        """Drop a deleted robot from the name cache (deleted by any replica)."""
        self._codes.pop(self._names.pop(code, None), None)

    def robot_count(self) -> int:
        return self._one("SELECT count(*) FROM robots")[0]

    def codebook(self) -> np.ndarray | None:
        row = self._one("SELECT n_clusters, dim, centroids FROM codebooks ORDER BY id DESC LIMIT 1")
        if row is None:
            return None
        return np.frombuffer(row[2], dtype=np.float32).reshape(row[0], row[1])

    def codebook_version(self) -> int:
        return self._one("SELECT coalesce(max(id), 0) FROM codebooks")[0]

    def save_codebook(self, centroids: np.ndarray) -> None:
        book = np.ascontiguousarray(centroids, np.float32)
        with self.conn() as con:
            con.execute(
                "INSERT INTO codebooks (created, n_clusters, dim, centroids) VALUES (%s,%s,%s,%s)",
                (time.time(), len(book), book.shape[1], book.tobytes()),
            )

    @contextlib.contextmanager
    def exclusive(self, what: str):
        """Held by one replica at a time (a session advisory lock); Conflict if taken.
        Yields `held()`: False once the session lost it (server restarted, link broken)."""
        with self.conn() as con:
            key = schema.LOCKS[what]
            if not con.execute("SELECT pg_try_advisory_lock(%s)", (key,)).fetchone()[0]:
                raise Conflict(f"A {what} is already running on another replica")
            try:
                yield lambda: schema.lock_held(con, key)
            finally:
                with contextlib.suppress(Exception):  # a lost session holds nothing
                    con.execute("SELECT pg_advisory_unlock(%s)", (key,))

    # --- keyframes ----------------------------------------------------------------

    def index_rows(self, batch: int = 10000, after: int = 0) -> Iterator[IndexRows]:
        """Stored keyframes' summary columns with id > after, in id order, in batches."""
        while True:
            rows = self._all(
                "SELECT id, robot, stamp, gist, bow_ids, bow_counts FROM keyframes "
                "WHERE id > %s ORDER BY id LIMIT %s",
                (after, batch),
            )
            if not rows:
                return
            after = rows[-1][0]
            yield IndexRows.from_rows(rows)
            if len(rows) < batch:
                return  # that was the last batch: no round trip to find it empty

    def deletions_after(self, after: int) -> list[tuple[int, int]]:
        """(deletion id, robot code) of robots deleted since `after`, by any replica."""
        return self._all("SELECT id, robot FROM deletions WHERE id > %s ORDER BY id", (after,))

    def _commit(self, batch: list[Pending]) -> list[Pending]:
        """A batch in one transaction, under the cluster-wide ingest lock (ids in commit order
        across replicas)."""
        if self._refused_when_closed(batch):
            return []
        added: dict[tuple[str, float], Pending] = {}
        try:
            with self.conn() as con, con.transaction():
                con.execute("SELECT pg_advisory_xact_lock(%s)", (schema.LOCKS["ingest"],))
                by_robot: dict[str, list[Pending]] = {}
                for it in batch:
                    by_robot.setdefault(it.robot_id, []).append(it)
                for name, items in by_robot.items():
                    code = self._codes.get(name) or schema.robot_code(con, name)
                    schema.insert_frames(con, code, items, added)
        except BaseException as exc:
            for it in batch:
                it.result = None
                it.error = exc if isinstance(exc, Exception) else Unavailable("interrupted")
            raise
        finally:
            for it in batch:
                it.done = True
        return list(added.values())

    def frame_bytes(self, kf_id: int) -> bytes:
        """The stored encoded frame of a keyframe, its CRC-32 checked."""
        row = self._one("SELECT data FROM keyframes WHERE id=%s", (int(kf_id),))
        return checked_frame(self, kf_id, row)

    def keyframe_info(self, kf_id: int) -> dict:
        row = self._one(
            "SELECT k.id, r.name, k.stamp, k.processed, length(k.data) FROM keyframes k "
            "JOIN robots r ON r.id = k.robot WHERE k.id=%s",
            (int(kf_id),),
        )
        if row is None:
            raise UnknownKeyframe(f"Unknown keyframe {kf_id}")
        return dict(zip(("id", "robot_id", "stamp", "processed", "bytes"), row, strict=True))

    def robots(self) -> list[dict]:
        rows = self._all(
            "SELECT r.name, count(k.id), min(k.stamp), max(k.stamp) FROM robots r "
            "LEFT JOIN keyframes k ON k.robot = r.id GROUP BY r.id ORDER BY r.name"
        )
        return [
            {"robot_id": n, "keyframes": c, "first_stamp": a, "last_stamp": b}
            for n, c, a, b in rows
        ]

    def keyframes(self, code: int, offset: int, limit: int) -> list[dict]:
        rows = self._all(
            "SELECT id, stamp, processed FROM keyframes WHERE robot=%s ORDER BY stamp "
            "LIMIT %s OFFSET %s",
            (code, int(limit), int(offset)),
        )
        return [{"id": i, "stamp": s, "processed": bool(p)} for i, s, p in rows]

    def robot_keyframe_ids(self, code: int) -> list[int]:
        rows = self._all("SELECT id FROM keyframes WHERE robot=%s ORDER BY stamp", (code,))
        return [r[0] for r in rows]

    # --- overlaps, the overlap queue and links ----------------------------------------

    def overlap_rows(self, code_a: int, code_b: int) -> list[OverlapRow]:
        return [OverlapRow(*r) for r in self._all(schema.OVERLAPS_SQL, (code_a, code_b) * 2)]

    def overlap_counts(self) -> list[tuple[int, int, int, int, int]]:
        return self._all(
            "SELECT robot_a, robot_b, count(*), max(inliers), sum(inliers) FROM overlap_pairs "
            "GROUP BY robot_a, robot_b"
        )

    def overlap_total(self) -> int:
        return self._one("SELECT count(*) FROM overlap_pairs")[0]

    def pending_count(self) -> int:
        return self._one(
            "SELECT count(*) FROM keyframes WHERE NOT processed AND attempts < %s",
            (MAX_ATTEMPTS,),
        )[0]

    def parked(self) -> dict[int, str]:
        sql = "SELECT id FROM keyframes WHERE NOT processed AND attempts >= %s ORDER BY id "
        rows = self._all(sql + "DESC LIMIT 100", (MAX_ATTEMPTS,))
        return {r[0]: f"overlap detection failed {MAX_ATTEMPTS} times" for r in rows}

    def claim(self, compute: Callable[[int], tuple | None]) -> int | None:
        """Claim the oldest unprocessed keyframe no other replica holds, run `compute` on
        it and record the result in the same transaction. `compute(kf_id)` returns (code,
        winners, link rows), or None for a keyframe deleted meanwhile. Returns the id, or
        None when the queue is empty. A failure of `compute` counts an attempt."""
        failed = None
        with self.conn() as con:
            with con.transaction():
                row = con.execute(
                    "SELECT id FROM keyframes WHERE NOT processed AND attempts < %s "
                    "ORDER BY id LIMIT 1 FOR NO KEY UPDATE SKIP LOCKED",
                    (MAX_ATTEMPTS,),
                ).fetchone()
                if row is None:
                    return None
                kf = row[0]
                try:
                    result = compute(kf)
                except Unavailable:
                    raise  # the database, not the keyframe: no attempt counted
                except Exception as exc:  # counted below, outside the rolled-back claim
                    failed = exc
                else:
                    if result is not None:
                        schema.record(con, kf, *result)
                    con.execute("UPDATE keyframes SET processed=true WHERE id=%s", (kf,))
            if failed is not None:
                con.execute("UPDATE keyframes SET attempts = attempts + 1 WHERE id=%s", (kf,))
                raise failed
        return kf

    def record_overlaps(
        self, kf_id: int, code: int, winners: list[WinnerRow], links: list[LinkRow]
    ) -> bool:
        with self.conn() as con, con.transaction():
            schema.record(con, kf_id, code, winners, links)
            con.execute("UPDATE keyframes SET processed=true WHERE id=%s", (kf_id,))
        return True

    def put_link(self, code_a: int, code_b: int, T_a_b: np.ndarray, rows: list[LinkRow]) -> int:
        """Store the link and its overlaps (one replica at a time: an advisory lock)."""
        import psycopg

        try:
            with self.conn() as con, con.transaction():
                con.execute("SELECT pg_advisory_xact_lock(%s)", (schema.LOCKS["links"],))
                return schema.put_link(con, code_a, code_b, np.asarray(T_a_b, "<f8"), rows)
        except psycopg.errors.ForeignKeyViolation as exc:
            raise Conflict("A robot was deleted while the link was registered") from exc

    def links(self, code: int | None = None) -> list[tuple[int, int, np.ndarray, float]]:
        sql = "SELECT robot_a, robot_b, transform, created FROM links"
        rows = (
            self._all(sql)
            if code is None
            else self._all(sql + " WHERE robot_a=%s OR robot_b=%s", (code, code))
        )
        return [(a, b, np.frombuffer(t, "<f8").reshape(4, 4), c) for a, b, t, c in rows]

    # --- administration ----------------------------------------------------------------

    def delete_robot(self, code: int, then: Callable[[np.ndarray], None]) -> int:
        with self._write_lock:
            with self.conn() as con, con.transaction():
                ids = schema.delete_robot(con, code, self.robot_name(code))
            then(ids)
            self.forget_robot(code)
        return len(ids)

    def view_bytes(self, kf_id: int) -> tuple[bytes, bytes] | None:
        row = self._one("SELECT rgb, depth FROM views WHERE kf=%s", (int(kf_id),))
        return None if row is None else (bytes(row[0]), bytes(row[1]))

    def view_ids(self, code: int) -> list[int]:
        sql = "SELECT k.id FROM keyframes k JOIN views v ON v.kf = k.id WHERE k.robot=%s "
        return [r[0] for r in self._all(sql + "ORDER BY k.stamp", (code,))]

    def live_get(self, key: str) -> str | None:
        row = self._one("SELECT value FROM live WHERE key=%s", (key,))
        return None if row is None else row[0]

    def live_put(self, key: str, value: str) -> None:
        with self.conn() as con:
            con.execute(schema.LIVE_PUT, (key, value))

    def live_cas(self, key: str, old: str | None, new: str) -> bool:
        with self.conn() as con:
            return schema.live_cas(con, key, old, new)

    def ping(self) -> bool:
        with contextlib.suppress(Unavailable):
            return self._one("SELECT 1") == (1,)
        return False

    def size_bytes(self) -> int:
        return self._one("SELECT pg_database_size(current_database())")[0]

    def refuse_writes(self) -> None:
        with self._write_lock:
            self._closed = True

    def close(self) -> None:
        self.refuse_writes()
        self.pool.close()
