"""The PostgreSQL schema of the place database and the statements that write it (each
called inside a transaction of `fleetmap.place.postgres.PostgresStore`)."""

from __future__ import annotations

import time
from urllib.parse import urlsplit

import numpy as np

from fleetmap.errors import BadInput, Conflict, Unavailable
from fleetmap.place.store import LinkRow, Pending, WinnerRow

SCHEMA_VERSION = 1
#: advisory lock keys, one per job only one replica may do at a time
LOCKS = {
    "schema": 0x464D_0001,
    "ingest": 0x464D_0002,  # keyframe ids in commit order
    "links": 0x464D_0003,
    "retraining": 0x464D_0004,
    "live map": 0x464D_0005,
}
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS robots (
    id SERIAL PRIMARY KEY, name TEXT NOT NULL UNIQUE, created DOUBLE PRECISION NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    id BIGSERIAL PRIMARY KEY,
    robot INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    stamp DOUBLE PRECISION NOT NULL, created DOUBLE PRECISION NOT NULL,
    processed BOOLEAN NOT NULL DEFAULT false, attempts SMALLINT NOT NULL DEFAULT 0,
    gist BYTEA NOT NULL, bow_ids BYTEA NOT NULL, bow_counts BYTEA NOT NULL, data BYTEA NOT NULL,
    UNIQUE (robot, stamp));
CREATE INDEX IF NOT EXISTS keyframes_queue ON keyframes(id) WHERE NOT processed;
CREATE TABLE IF NOT EXISTS overlap_pairs (
    kf_a BIGINT NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
    kf_b BIGINT NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
    robot_a INTEGER NOT NULL, robot_b INTEGER NOT NULL,
    inliers INTEGER NOT NULL, matches INTEGER NOT NULL, created DOUBLE PRECISION NOT NULL,
    source TEXT NOT NULL DEFAULT 'cascade',
    PRIMARY KEY (kf_a, kf_b));
CREATE INDEX IF NOT EXISTS overlaps_robots ON overlap_pairs(robot_a, robot_b);
CREATE INDEX IF NOT EXISTS overlaps_b ON overlap_pairs(kf_b);
CREATE TABLE IF NOT EXISTS links (
    robot_a INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    robot_b INTEGER NOT NULL REFERENCES robots(id) ON DELETE CASCADE,
    transform BYTEA NOT NULL, created DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (robot_a, robot_b));
CREATE TABLE IF NOT EXISTS codebooks (
    id SERIAL PRIMARY KEY, created DOUBLE PRECISION NOT NULL, n_clusters INTEGER NOT NULL,
    dim INTEGER NOT NULL, centroids BYTEA NOT NULL);
CREATE TABLE IF NOT EXISTS views (
    kf BIGINT PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
    rgb BYTEA NOT NULL, depth BYTEA NOT NULL);
CREATE TABLE IF NOT EXISTS live (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS deletions (
    id BIGSERIAL PRIMARY KEY, robot INTEGER NOT NULL, created DOUBLE PRECISION NOT NULL);
"""
LIVE_PUT = "INSERT INTO live VALUES (%s, %s) ON CONFLICT (key) DO UPDATE SET value = EXCLUDED.value"
OVERLAPS_SQL = (
    "SELECT o.kf_a, ka.stamp, o.robot_a, o.kf_b, kb.stamp, o.robot_b, o.inliers, o.matches, "
    "o.source FROM overlap_pairs o JOIN keyframes ka ON ka.id=o.kf_a "
    "JOIN keyframes kb ON kb.id=o.kf_b "
    "WHERE (o.robot_a=%s AND o.robot_b=%s) OR (o.robot_b=%s AND o.robot_a=%s)"
)


def redacted(url: str) -> str:
    """host:port/database of a URL, never its password."""
    u = urlsplit(url)
    return f"{u.hostname or 'localhost'}:{u.port or 5432}{u.path or ''}"


def create(con, vocab_id: str, where: str) -> None:
    """The schema, created once whichever replica starts first (an advisory lock); refuse
    a database of another schema version or vocabulary."""
    con.execute("SELECT pg_advisory_lock(%s)", (LOCKS["schema"],))
    try:
        con.execute(SCHEMA)
        _store_frames_uncompressed(con)
        con.execute(
            "INSERT INTO meta VALUES ('schema_version', %s), ('vocab_id', %s) "
            "ON CONFLICT (key) DO NOTHING",
            (str(SCHEMA_VERSION), vocab_id),
        )
        meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
    finally:
        con.execute("SELECT pg_advisory_unlock(%s)", (LOCKS["schema"],))
    if int(meta["schema_version"]) != SCHEMA_VERSION:
        raise BadInput(
            f"{where}: schema version {meta['schema_version']}, this build uses {SCHEMA_VERSION}"
        )
    if meta["vocab_id"] != vocab_id:
        raise BadInput(f"{where} was built with vocabulary {meta['vocab_id']}, not {vocab_id}")


def robot_code(con, name: str) -> int:
    """The robot's id, the robot created if new (by this or any replica)."""
    row = con.execute(
        "INSERT INTO robots (name, created) VALUES (%s, %s) ON CONFLICT (name) DO NOTHING "
        "RETURNING id",
        (name, time.time()),
    ).fetchone()
    return (
        row[0] if row else con.execute("SELECT id FROM robots WHERE name=%s", (name,)).fetchone()[0]
    )


def _store_frames_uncompressed(con) -> None:
    """Encoded frames are compact binary (uint8 descriptors, float16 GIST): PostgreSQL's
    pglz only spends CPU on them. Measured in-process, 800 keyframes in batches of 8: 572
    keyframes/s with the default storage, 1,386 with EXTERNAL (out of line, uncompressed)."""
    row = con.execute(
        "SELECT attstorage FROM pg_attribute WHERE attrelid = 'keyframes'::regclass "
        "AND attname = 'data'"
    ).fetchone()
    if row and row[0] != "e":
        con.execute("ALTER TABLE keyframes ALTER COLUMN data SET STORAGE EXTERNAL")


def insert_frames(con, code: int, items: list[Pending], added: dict) -> None:
    """Frames of robot `code` in a batch, in two round trips: each stored, found identical
    (idempotent), or a Conflict. `added` maps (robot, stamp) to the frames stored."""
    rows = con.execute(
        "SELECT stamp, id, data FROM keyframes WHERE robot=%s AND stamp = ANY(%s)",
        (code, [it.frame.stamp for it in items]),
    ).fetchall()
    stored = {stamp: (kf, bytes(data)) for stamp, kf, data in rows}
    fresh, twins = [], []
    for it in items:
        key = (it.robot_id, it.frame.stamp)
        first = added.get(key)
        same = stored[key[1]][1] if key[1] in stored else first.data if first else None
        if same is not None and same != it.data:
            it.error = Conflict(
                f"Robot {it.robot_id!r} already has a different keyframe at stamp {key[1]}"
            )
        elif key[1] in stored:
            it.result = (int(stored[key[1]][0]), False)
            _insert_view(con, it)
        elif first is not None:
            twins.append(it)  # sent twice in this batch: the first one's id
        else:
            fresh.append(it)
            added[key] = it
    if fresh:
        cur = con.cursor()
        cur.executemany(
            "INSERT INTO keyframes (robot, stamp, created, gist, bow_ids, bow_counts, data) "
            "VALUES (%s, %s, %s, %s, %s, %s, %s) RETURNING id",
            [_keyframe_row(code, it) for it in fresh],
            returning=True,
        )
        for it in fresh:
            it.result = (int(cur.fetchone()[0]), True)
            cur.nextset()
        for it in fresh:
            _insert_view(con, it)
    for it in twins:
        it.result = (added[(it.robot_id, it.frame.stamp)].result[0], False)


def _insert_view(con, it: Pending) -> None:
    if it.view is not None:
        con.execute(
            "INSERT INTO views VALUES (%s, %s, %s) ON CONFLICT (kf) DO NOTHING",
            (it.result[0], *it.view),
        )


def _keyframe_row(code: int, it: Pending) -> tuple:
    f = it.frame
    return (
        code,
        f.stamp,
        time.time(),
        f.gist.astype("<f2").tobytes(),
        f.bow_ids.astype("<u4").tobytes(),
        f.bow_counts.astype("<u2").tobytes(),
        it.data,
    )


def record(con, kf_id: int, code: int, winners: list[WinnerRow], links: list[LinkRow]) -> None:
    """One keyframe's verified winners and link overlaps."""
    now = time.time()
    for kf_b, code_b, inliers, matches in winners:
        con.execute(
            "INSERT INTO overlap_pairs (kf_a, kf_b, robot_a, robot_b, inliers, matches, created) "
            "VALUES (%s, %s, %s, %s, %s, %s, %s) ON CONFLICT (kf_a, kf_b) DO UPDATE SET "
            "inliers = EXCLUDED.inliers, matches = EXCLUDED.matches, source = 'cascade'",
            (kf_id, kf_b, code, code_b, inliers, matches, now),
        )
    insert_link_rows(con, links, now)


def insert_link_rows(con, rows: list[LinkRow], now: float) -> int:
    n = 0
    for kx, rx, ky, ry, seen, total in rows:
        hit = con.execute(
            "SELECT 1 FROM overlap_pairs WHERE (kf_a=%s AND kf_b=%s) OR (kf_a=%s AND kf_b=%s)",
            (kx, ky, ky, kx),
        ).fetchone()
        if hit is None:
            con.execute(
                "INSERT INTO overlap_pairs VALUES (%s, %s, %s, %s, %s, %s, %s, 'link')",
                (kx, ky, rx, ry, seen, total, now),
            )
            n += 1
    return n


def put_link(con, code_a: int, code_b: int, T_a_b: np.ndarray, rows: list[LinkRow]) -> int:
    now = time.time()
    con.execute(
        "INSERT INTO links VALUES (%s, %s, %s, %s) ON CONFLICT (robot_a, robot_b) "
        "DO UPDATE SET transform = EXCLUDED.transform, created = EXCLUDED.created",
        (code_a, code_b, T_a_b.tobytes(), now),
    )
    con.execute(
        "DELETE FROM overlap_pairs WHERE source='link' AND "
        "((robot_a=%s AND robot_b=%s) OR (robot_a=%s AND robot_b=%s))",
        (code_a, code_b, code_b, code_a),
    )
    return insert_link_rows(con, rows, now)


def delete_robot(con, code: int, name: str | None = None) -> np.ndarray:
    """Delete a robot with its keyframes, overlaps, links and the live map's states
    derived from it; log it for the other replicas' indexes. Returns the keyframe ids
    removed."""
    ids = np.array(
        [r[0] for r in con.execute("SELECT id FROM keyframes WHERE robot=%s", (code,))],
        dtype=np.int64,
    )
    con.execute("DELETE FROM overlap_pairs WHERE robot_a=%s OR robot_b=%s", (code, code))
    con.execute("DELETE FROM links WHERE robot_a=%s OR robot_b=%s", (code, code))
    con.execute("DELETE FROM keyframes WHERE robot=%s", (code,))
    con.execute("DELETE FROM robots WHERE id=%s", (code,))
    con.execute("INSERT INTO deletions (robot, created) VALUES (%s, %s)", (code, time.time()))
    if name is not None:
        _forget_live(con, name)
    return ids


def _forget_live(con, name: str) -> None:
    """In the delete's transaction: the live map's rows without what robot `name` gave
    (rows locked, so a compare-and-set of another replica waits and then fails)."""
    from fleetmap.fleet.state import forget_robot

    sql = "SELECT key, value FROM live WHERE key IN ('pairs', 'map') FOR UPDATE"
    rows = dict(con.execute(sql).fetchall())
    new = forget_robot(rows.get("pairs"), rows.get("map"), name)
    for key, value in zip(("pairs", "map"), new, strict=True):
        if value is not None:
            con.execute(LIVE_PUT, (key, value))


def lock_held(con, key: int) -> bool:
    """This session still holds the advisory lock `key` (False if the session is gone)."""
    sql = (
        "SELECT count(*) FROM pg_locks WHERE locktype='advisory' AND granted "
        "AND pid=pg_backend_pid() AND classid::bigint=%s AND objid::bigint=%s AND objsubid=1"
    )
    try:
        return con.execute(sql, (key >> 32, key & 0xFFFFFFFF)).fetchone()[0] > 0
    except Exception:  # the connection broke: the server dropped the session and its locks
        return False


def live_cas(con, key: str, old: str | None, new: str) -> bool:
    """Set a live row to `new` if it still holds `old` (None: absent); True if it was set."""
    if old is None:
        sql = "INSERT INTO live VALUES (%s, %s) ON CONFLICT (key) DO NOTHING"
        return con.execute(sql, (key, new)).rowcount == 1
    sql = "UPDATE live SET value=%s WHERE key=%s AND value=%s"
    return con.execute(sql, (new, key, old)).rowcount == 1


def check_reachable(url: str, timeout_s: int = 5) -> None:
    """Connect once; Unavailable naming the server (never the password) if it fails."""
    import psycopg

    try:
        psycopg.connect(url, connect_timeout=timeout_s).close()
    except psycopg.Error as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise Unavailable(f"PostgreSQL at {redacted(url)} is unreachable: {first}") from None
