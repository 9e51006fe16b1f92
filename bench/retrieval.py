"""Place database at scale: cascade vs brute-force BoW, stage fractions, ingest, memory.

    .venv/bin/python bench/retrieval.py [--sizes 1000 10000 100000] [--http-frames 2000]

The database holds the real frames (RTAB-Map corridor, SUN3D study room) plus synthetic
keyframes made to look like real ones: GIST mixed from two real GISTs plus noise, 300
features whose descriptors are noisy copies of visual words drawn with the real word
frequencies (the drawn words are their bag of words). Queries are the real revisit queries
(corridor second lap, SUN3D robot B), so recall is measured on ground truth while the
distractors grow. The brute-force
baseline scores the query's BoW against every stored keyframe (the thesis's
visual-similarity-matrix method, vectorised) and verifies its best candidates exactly as
the cascade does.
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
from tqdm import tqdm

from fleetmap.dataset import read_recording
from fleetmap.extract import FrameExtractor, extract_recording
from fleetmap.frame import Frame, encode
from fleetmap.place import DEFAULT_CASCADE, Filter, PlaceDB, RetrainPolicy
from fleetmap.place.cascade import local_stage
from fleetmap.vocabulary import load_vocabulary

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def real_frames(vocab):
    x = FrameExtractor(vocab)
    cor = [
        x("corridor", float(i), cv2.imread(str(DATA / f"rtabmap_corridor/images/{i}.jpg")))
        for i in range(1, 85)
    ]
    sun = {
        r: list(extract_recording(read_recording(DATA / "sun3d_studyroom" / r), x))
        for r in ("robot_a", "robot_b")
    }
    gt = {}
    for line in (DATA / "rtabmap_corridor/gt_loop_pairs.csv").read_text().splitlines():
        if line and not line.startswith("#"):
            q, m = map(int, line.split(","))
            gt.setdefault(q, set()).add(float(m))
    return cor, sun, gt


class Synth:
    """Realistic synthetic keyframes from the statistics of real ones."""

    def __init__(self, vocab, reals: list[Frame], seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.vocab = vocab
        self.gists = np.stack([f.gist.astype(np.float32) for f in reals])
        freq = np.zeros(vocab.n_words)
        for f in reals:
            freq[f.bow_ids] += f.bow_counts
        self.p = (freq + 1) / (freq + 1).sum()

    def frame(self, robot: str, stamp: float, n: int = 300) -> Frame:
        r = self.rng
        i, j = r.integers(len(self.gists), size=2)
        a = r.uniform(0.2, 0.8)
        g = a * self.gists[i] + (1 - a) * self.gists[j]
        g = g + r.normal(0, 0.25 * g.std(), g.shape)
        g = np.abs(g) / np.linalg.norm(g)
        words = r.choice(self.vocab.n_words, size=n, p=self.p)
        desc = self.vocab.word_centroids[words] + r.normal(0, 12, (n, 128))
        desc = np.clip(np.round(desc), 0, 255).astype(np.uint8)
        # the drawn words are the BoW: re-quantising these noisy copies returns the same word
        # (3,000 of 3,000 checked), and skipping it makes the fill about 10x faster
        ids, counts = np.unique(words, return_counts=True)
        ids, counts = ids.astype(np.uint32), counts.astype(np.uint16)
        kp = r.uniform([0, 0], [639, 479], (n, 2)).astype(np.float32)
        pts = r.normal(0, 3, (n, 3)).astype(np.float32)
        return Frame(
            robot_id=robot,
            stamp=stamp,
            gist=g.astype(np.float16),
            keypoints=kp,
            descriptors=desc,
            bow_ids=ids,
            bow_counts=counts,
            T_map_cam=np.eye(4),
            points=pts,
            point_valid=np.ones(n, bool),
            vocab_id=self.vocab.vocab_id,
        )


def evaluate(db: PlaceDB, cor, sun, gt) -> dict:
    """Cascade and brute force on the real queries; latency, recall, stage fractions."""
    cor_id = db.robot_code("corridor")
    a_id = db.robot_code("robot_a")
    queries = [
        (cor[q - 1], Filter(robots={cor_id}, max_stamp=q - 5.5), gt.get(q)) for q in range(41, 85)
    ] + [(f, Filter(robots={a_id}), None) for f in sun["robot_b"]]
    out = {
        "cascade_ms": [],
        "brute_ms": [],
        "stage_frac": [],
        "stage_ms": [],
        "hits": 0,
        "brute_hits": 0,
        "false": 0,
        "brute_false": 0,
        "sun_found": 0,
        "brute_sun_found": 0,
    }
    n = len(db.index)
    p = DEFAULT_CASCADE
    for frame, flt, truth in queries:
        r = db.query(frame, flt)
        out["cascade_ms"].append(r.total_ms)
        out["stage_frac"].append([s.kept / n for s in r.stages])
        out["stage_ms"].append([s.ms for s in r.stages])
        t = time.perf_counter()
        cands = db.index.brute_force_bow(frame.bow_ids, frame.bow_counts, flt, p.max_verify)
        verified, _ = local_stage(frame, cands, db.index, db.load_frame, p)
        out["brute_ms"].append(1000 * (time.perf_counter() - t))
        for key, win in (("", r.winner), ("brute_", verified[0] if verified else None)):
            if win is None:
                continue
            if truth is None:
                out[key + "sun_found"] += 1
            elif win.stamp in truth:
                out[key + "hits"] += 1
            else:
                out[key + "false"] += 1
    return out


def http_ingest(chunks: list[list[bytes]], tmp: Path) -> float:
    """Durable ingest throughput over HTTP, one concurrent client per chunk (kf/s)."""
    import sys

    sys.path.insert(0, str(ROOT))
    from tests.servers import Service

    svc = Service("place-db", tmp / "http").start()
    try:
        errors = []

        def run(k: int) -> None:
            with httpx.Client(base_url=svc.url, timeout=60) as c:
                for d in chunks[k]:
                    r = c.post(
                        f"/robots/bench{k}/keyframes",
                        content=d,
                        headers={"content-type": "application/octet-stream"},
                    )
                    if r.status_code != 201:
                        errors.append(r.status_code)

        threads = [threading.Thread(target=run, args=(k,)) for k in range(len(chunks))]
        t = time.perf_counter()
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        rate = sum(map(len, chunks)) / (time.perf_counter() - t)
        if errors:
            raise RuntimeError(f"{len(errors)} failed posts: {set(errors)}")
        return rate
    finally:
        svc.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--http-frames", type=int, default=2000)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    vocab = load_vocabulary()
    cor, sun, gt = real_frames(vocab)
    reals = cor + sun["robot_a"] + sun["robot_b"]
    synth = Synth(vocab, reals)
    tmp = Path(args.workdir or tempfile.mkdtemp(prefix="fleetmap-bench-"))
    tmp.mkdir(parents=True, exist_ok=True)

    print(f"HTTP ingest: {args.http_frames} keyframes from 8 concurrent clients ...")
    per = args.http_frames // 8
    http_frames = [
        [encode(synth.frame(f"bench{k}", float(i))) for i in range(per)] for k in range(8)
    ]
    rate = http_ingest(http_frames, tmp)
    print(f"  {rate:.0f} keyframes/s durable (synchronous=FULL)")

    db = PlaceDB(
        tmp / "scale.sqlite", vocab, retrain=RetrainPolicy(enabled=False), background=False
    )
    db.add_keyframes("corridor", [encode(f) for f in cor])
    for r, fs in sun.items():
        db.add_keyframes(r, [encode(f) for f in fs])
    rows = []
    stamp = 1e6
    for size in sorted(args.sizes):
        need = size - len(db.index)
        with tqdm(total=max(need, 0), desc=f"fill {size}", unit="kf") as bar:
            while need > 0:
                k = min(need, 2000)
                by_robot = {}
                for i in range(k):
                    robot = f"synth{int(stamp + i) % 50}"
                    by_robot.setdefault(robot, []).append(encode(synth.frame(robot, stamp + i)))
                for robot, ds in by_robot.items():
                    db.add_keyframes(robot, ds)
                stamp += k
                need -= k
                bar.update(k)
        info = db.retrain()
        gc.collect()
        ev = evaluate(db, cor, sun, gt)
        fr = np.mean(ev["stage_frac"], axis=0)
        rows.append((size, info["clusters"], ev, fr))
        print(
            f"{size}: cascade p50 {np.median(ev['cascade_ms']):.1f} ms p99 "
            f"{np.percentile(ev['cascade_ms'], 99):.1f} | brute p50 "
            f"{np.median(ev['brute_ms']):.1f} p99 {np.percentile(ev['brute_ms'], 99):.1f} | "
            f"corridor hits {ev['hits']}/{len(gt)} false {ev['false']} (brute {ev['brute_hits']}"
            f"/{ev['brute_false']}) | sun3d {ev['sun_found']}/{len(sun['robot_b'])} (brute "
            f"{ev['brute_sun_found']}) | kept {np.round(100 * fr, 3)} % | stage ms (median) "
            f"{np.round(np.median(ev['stage_ms'], axis=0), 2)}"
        )
    db.close()

    # resident memory per keyframe: a fresh process-local index rebuilt from the database
    gc.collect()
    before = rss_mb()
    t = time.perf_counter()
    again = PlaceDB(
        tmp / "scale.sqlite", vocab, retrain=RetrainPolicy(enabled=False), background=False
    )
    load_s = time.perf_counter() - t
    per_kf = (rss_mb() - before) * 1024 * 1024 / len(again.index)
    print(
        f"index rebuilt from SQLite in {load_s:.1f} s: {per_kf:.0f} B resident per keyframe "
        f"({len(again.index)} keyframes); database file "
        f"{(tmp / 'scale.sqlite').stat().st_size / 1e9:.2f} GB"
    )
    again.close()

    print(
        "\n| keyframes | clusters | cascade p50 / p99 | brute-force p50 / p99 | speed-up (p50) |"
        " kept: clusters / GIST tr / inverted file / BoW / matched / verified | corridor hits, "
        "false (cascade; brute) | SUN3D B found (cascade; brute) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size, k, ev, fr in rows:
        c50, c99 = np.median(ev["cascade_ms"]), np.percentile(ev["cascade_ms"], 99)
        b50, b99 = np.median(ev["brute_ms"]), np.percentile(ev["brute_ms"], 99)
        kept = " / ".join(f"{100 * x:.3g}%" for x in fr)
        print(
            f"| {size:,} | {k} | {c50:.1f} / {c99:.1f} ms | {b50:.1f} / {b99:.1f} ms | "
            f"{b50 / c50:.1f}x | {kept} | {ev['hits']}/{len(gt)}, {ev['false']}; "
            f"{ev['brute_hits']}/{len(gt)}, {ev['brute_false']} | {ev['sun_found']}/"
            f"{len(sun['robot_b'])}; {ev['brute_sun_found']}/{len(sun['robot_b'])} |"
        )
    print(
        f"\nHTTP ingest, 8 concurrent clients: {rate:.0f} keyframes/s; resident memory "
        f"{per_kf:.0f} B per keyframe; pid {os.getpid()}"
    )


if __name__ == "__main__":
    main()
