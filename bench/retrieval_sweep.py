"""Recall against speed at scale: the cascade's probed clusters m and its inverted file
(how many of the query's words it reads, how many candidates it may add) on a database that
`bench/retrieval.py --workdir DIR` already filled (100k keyframes).

    .venv/bin/python bench/retrieval_sweep.py --workdir /tmp/fmbench --m 64 128 192 \\
        --ivf-candidates 0 12

Same queries and brute-force baseline as bench/retrieval.py (corridor second-lap revisits,
SUN3D robot B against robot A), one line per setting; `--ivf-candidates 0` is the cascade
without the inverted file. The index is rebuilt from the database once (its time and
resident memory per keyframe are printed) and every setting queries it.
"""

from __future__ import annotations

import argparse
import gc
import itertools
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from retrieval import evaluate, real_frames, rss_mb  # noqa: E402

from fleetmap.place import (  # noqa: E402
    DEFAULT_CASCADE,  # noqa: E402
    PlaceDB,
    RetrainPolicy,
)
from fleetmap.vocabulary import load_vocabulary  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workdir", type=Path, required=True)
    ap.add_argument("--m", type=int, nargs="+", default=[64, 128, 192])
    ap.add_argument("--ivf-words", type=int, nargs="+", default=[DEFAULT_CASCADE.ivf_words])
    ap.add_argument(
        "--ivf-candidates", type=int, nargs="+", default=[DEFAULT_CASCADE.ivf_candidates]
    )
    args = ap.parse_args()
    vocab = load_vocabulary()
    cor, sun, gt = real_frames(vocab)
    gc.collect()
    before, t = rss_mb(), time.perf_counter()
    db = PlaceDB(
        args.workdir / "scale.sqlite",
        vocab,
        retrain=RetrainPolicy(enabled=False),
        background=False,
    )
    load_s, n = time.perf_counter() - t, len(db.index)
    per_kf = (rss_mb() - before) * 1024 * 1024 / n
    print(
        f"index rebuilt from SQLite in {load_s:.1f} s: {per_kf:.0f} B resident per keyframe, "
        f"{len(db.index.postings):,} postings in {len(db.index.postings.segments)} segments"
    )
    print(
        "\n| m | words | inverted-file candidates | keyframes | cascade p50 / p99 | brute p50 "
        "| speed-up | corridor hits, false (cascade; brute) | SUN3D (cascade; brute) | kept by "
        "the GIST stage / with the inverted file | stage ms: global / inverted file / BoW / "
        "SIFT / epipolar |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for m, words, cands in itertools.product(args.m, args.ivf_words, args.ivf_candidates):
        db.params = replace(DEFAULT_CASCADE, m_clusters=m, ivf_words=words, ivf_candidates=cands)
        ev = evaluate(db, cor, sun, gt)
        fr = np.mean(ev["stage_frac"], axis=0)
        ms = np.median(ev["stage_ms"], axis=0)
        c50, c99 = np.median(ev["cascade_ms"]), np.percentile(ev["cascade_ms"], 99)
        b50 = np.median(ev["brute_ms"])
        print(
            f"| {m} | {words} | {cands} | {n:,} | {c50:.1f} / {c99:.1f} ms | {b50:.0f} ms | "
            f"{b50 / c50:.0f}x | {ev['hits']}/44, {ev['false']}; {ev['brute_hits']}/44, "
            f"{ev['brute_false']} | {ev['sun_found']}; {ev['brute_sun_found']} | "
            f"{100 * fr[1]:.4f}% / {100 * fr[2]:.4f}% | {ms[0] + ms[1]:.1f} / {ms[2]:.1f} / "
            f"{ms[3]:.1f} / {ms[4]:.1f} / {ms[5]:.1f} |",
            flush=True,
        )
    db.close()


if __name__ == "__main__":
    main()
