"""The place database on SQLite and on PostgreSQL, with 1 and 2 replicas (issue 12).

    .venv/bin/python bench/pg_scaling.py [--sizes 10000 100000] [--http-frames 4000]
        [--worker-frames 1500]

Needs PostgreSQL 15's binaries (a throwaway cluster is started in a temporary folder, as
the tests do) and ../shared/data (real queries: corridor revisits, SUN3D robot B).

1. Durable ingest over HTTP: 8 clients posting synthetic keyframes (bench/retrieval.py's
   `Synth`) at once; SQLite (one process), PostgreSQL through 1 replica and through 2
   (clients split over both). Background overlap detection off, so this is storage alone.
2. Query latency and recall at each size: the same keyframes in both backends (filled
   in-process, chunk by chunk; the codebook retrained at k = 2 sqrt(N) and shared), the
   real revisit queries run against each (`db.query`: index in memory, candidates' frames
   read from storage). faiss and OpenCV single-threaded, as the service runs them.
3. The overlap worker: `--worker-frames` unprocessed keyframes added to the database of the
   largest size, worked down by 1 replica, then (same start) by 2; keyframes/s.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from retrieval import Synth, evaluate, real_frames  # noqa: E402

from fleetmap.frame import encode  # noqa: E402
from fleetmap.place import PlaceDB, RetrainPolicy  # noqa: E402
from fleetmap.vocabulary import load_vocabulary  # noqa: E402
from tests import pg  # noqa: E402
from tests.servers import Service  # noqa: E402

OCTET = {"content-type": "application/octet-stream"}
OFF = RetrainPolicy(enabled=False)


def replicas(n: int, env: dict, tmp: Path) -> list[Service]:
    return [Service("place-db", tmp / f"svc{k}", env=env).start(120) for k in range(n)]


def http_ingest(urls: list[str], chunks: list[list[bytes]]) -> float:
    """kf/s with one client per chunk, clients spread over the URLs."""
    errors: list = []

    def run(k: int) -> None:
        with httpx.Client(base_url=urls[k % len(urls)], timeout=120) as c:
            for d in chunks[k]:
                r = c.post(f"/robots/i{k}/keyframes", content=d, headers=OCTET)
                if r.status_code != 201:
                    errors.append((r.status_code, r.text[:200]))

    threads = [threading.Thread(target=run, args=(k,)) for k in range(len(chunks))]
    t = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    if errors:
        raise RuntimeError(f"{len(errors)} failed posts, e.g. {errors[0]}")
    return sum(map(len, chunks)) / (time.perf_counter() - t)


def ingest_rates(synth, n: int, cluster, tmp: Path) -> dict:
    per = n // 8
    out = {}
    for name, n_rep in (("sqlite", 1), ("postgres, 1 replica", 1), ("postgres, 2 replicas", 2)):
        chunks = [[encode(synth.frame(f"i{k}", float(i))) for i in range(per)] for k in range(8)]
        env = {"FLEETMAP_PLACE_DB_BACKGROUND_OVERLAPS": "false"}
        if name != "sqlite":
            env["FLEETMAP_PLACE_DB_DATABASE"] = cluster.database()
        svcs = replicas(n_rep, env, tmp / name.replace(" ", "_").replace(",", ""))
        try:
            out[name] = http_ingest([s.url for s in svcs], chunks)
        finally:
            for s in svcs:
                s.stop()
        print(f"ingest {name}: {out[name]:.0f} keyframes/s")
    return out


def fill(dbs: list[PlaceDB], synth, size: int, stamp: float) -> float:
    need = size - len(dbs[0].index)
    with tqdm(total=max(need, 0), desc=f"fill {size}", unit="kf") as bar:
        while need > 0:
            k = min(need, 2000)
            by_robot: dict[str, list[bytes]] = {}
            for i in range(k):
                robot = f"synth{int(stamp + i) % 50}"
                by_robot.setdefault(robot, []).append(encode(synth.frame(robot, stamp + i)))
            for db in dbs:
                for robot, ds in by_robot.items():
                    db.add_keyframes(robot, ds)
            stamp, need = stamp + k, need - k
            bar.update(k)
    return stamp


def worker_rate(url: str, n_replicas: int, tmp: Path, timeout: float = 1800) -> float:
    """kf/s of the overlap workers of n replicas working the queue down."""
    svcs = replicas(n_replicas, {"FLEETMAP_PLACE_DB_DATABASE": url}, tmp / f"w{n_replicas}")
    try:
        with httpx.Client(base_url=svcs[0].url, timeout=60) as c:
            start_pending = c.get("/healthz").json()["pending"]
            t = time.perf_counter()
            while (left := c.get("/healthz").json()["pending"]) > 0:
                if time.perf_counter() - t > timeout:
                    raise RuntimeError(f"{left} keyframes still pending")
                time.sleep(0.2)
            return start_pending / (time.perf_counter() - t)
    finally:
        for s in svcs:
            s.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--http-frames", type=int, default=4000)
    ap.add_argument("--worker-frames", type=int, default=1500)
    ap.add_argument("--ingest-only", action="store_true", help="part 1 alone")
    args = ap.parse_args()
    from fleetmap.services.place_db.main import single_threaded_kernels

    single_threaded_kernels()
    vocab = load_vocabulary()
    cor, sun, gt = real_frames(vocab)
    synth = Synth(vocab, cor + sun["robot_a"] + sun["robot_b"])
    tmp = Path(tempfile.mkdtemp(prefix="fleetmap-pgbench-"))
    cluster = pg.Cluster().start()
    try:
        rates = ingest_rates(synth, args.http_frames, cluster, tmp)
        if args.ingest_only:
            return
        url = cluster.database()
        dbs = [
            PlaceDB(tmp / "scale.sqlite", vocab, retrain=OFF, background=False),
            PlaceDB(url, vocab, retrain=OFF, background=False),
        ]
        for db in dbs:
            db.add_keyframes("corridor", [encode(f) for f in cor])
            for r, fs in sun.items():
                db.add_keyframes(r, [encode(f) for f in fs])
        stamp, rows = 1e6, []
        for size in sorted(args.sizes):
            stamp = fill(dbs, synth, size, stamp)
            book = dbs[0].retrain()  # k = 2 sqrt(N), as bench/retrieval.py; both the same
            dbs[1].index.set_codebook(dbs[0].index.codebook)
            dbs[1].store.save_codebook(dbs[0].index.codebook)
            print(f"{size}: codebook of {book['clusters']} clusters")
            for name, db in zip(("sqlite", "postgres"), dbs, strict=True):
                ev = evaluate(db, cor, sun, gt)
                ms = np.array(ev["cascade_ms"])
                rows.append((size, name, np.median(ms), np.percentile(ms, 99), ev["hits"], len(gt)))
                print(f"{size} {name}: query p50 {rows[-1][2]:.1f} ms p99 {rows[-1][3]:.1f} ms, "
                      f"corridor {ev['hits']}/{len(gt)}, false {ev['false']}")  # fmt: skip
        for db in dbs:
            db.close()
        # the overlap queue: the keyframes so far are marked done, new ones queued
        with __import__("psycopg").connect(url, autocommit=True) as con:
            con.execute("UPDATE keyframes SET processed = true")
        queued = PlaceDB(url, vocab, retrain=OFF, background=False)
        fill([queued], synth, len(queued.index) + args.worker_frames, stamp)
        queued.close()
        with __import__("psycopg").connect(url, autocommit=True) as con:
            con.execute("CREATE TABLE queue_copy AS SELECT id FROM keyframes WHERE NOT processed")
        w1 = worker_rate(url, 1, tmp)
        with __import__("psycopg").connect(url, autocommit=True) as con:
            con.execute("DELETE FROM overlap_pairs WHERE kf_a IN (SELECT id FROM queue_copy)")
            con.execute(
                "UPDATE keyframes SET processed = false WHERE id IN (SELECT id FROM queue_copy)"
            )
        w2 = worker_rate(url, 2, tmp)
        print(f"overlap worker: 1 replica {w1:.1f} kf/s, 2 replicas {w2:.1f} kf/s (x{w2 / w1:.2f})")
    finally:
        cluster.remove()

    print("\n| backend | durable ingest, 8 clients |")
    print("|---|---|")
    for name, r in rates.items():
        print(f"| {name} | {r:.0f} keyframes/s |")
    print("\n| keyframes | backend | query p50 / p99 | corridor revisits found |")
    print("|---|---|---|---|")
    for size, name, p50, p99, hits, n in rows:
        print(f"| {size} | {name} | {p50:.1f} / {p99:.1f} ms | {hits}/{n} |")
    print(f"\noverlap worker over {args.worker_frames} queued keyframes: 1 replica {w1:.1f} "
          f"kf/s, 2 replicas {w2:.1f} kf/s (x{w2 / w1:.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
