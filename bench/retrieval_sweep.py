"""Recall against speed at scale: the cascade's probed clusters m on a database that
`bench/retrieval.py --workdir DIR` already filled (100k keyframes).

    .venv/bin/python bench/retrieval_sweep.py --workdir /tmp/fmbench --m 64 128 192

Same queries and brute-force baseline as bench/retrieval.py (corridor second-lap revisits,
SUN3D robot B against robot A), one line per m.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from retrieval import evaluate, real_frames  # noqa: E402

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
    args = ap.parse_args()
    vocab = load_vocabulary()
    cor, sun, gt = real_frames(vocab)
    print(
        "| m | keyframes | cascade p50 / p99 | brute p50 | speed-up | corridor hits, false "
        "(cascade; brute) | SUN3D (cascade; brute) | kept by the GIST stage |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for m in args.m:
        db = PlaceDB(
            args.workdir / "scale.sqlite",
            vocab,
            params=replace(DEFAULT_CASCADE, m_clusters=m),
            retrain=RetrainPolicy(enabled=False),
            background=False,
        )
        ev = evaluate(db, cor, sun, gt)
        fr = np.mean(ev["stage_frac"], axis=0)
        c50, c99 = np.median(ev["cascade_ms"]), np.percentile(ev["cascade_ms"], 99)
        b50 = np.median(ev["brute_ms"])
        print(
            f"| {m} | {len(db.index):,} | {c50:.1f} / {c99:.1f} ms | {b50:.0f} ms | "
            f"{b50 / c50:.0f}x | {ev['hits']}/44, {ev['false']}; {ev['brute_hits']}/44, "
            f"{ev['brute_false']} | {ev['sun_found']}; {ev['brute_sun_found']} | "
            f"{100 * fr[1]:.4f}% |",
            flush=True,
        )
        db.close()


if __name__ == "__main__":
    main()
