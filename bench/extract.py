"""Per-frame cost of the frame structure on real 640x480 RGB-D frames.

    .venv/bin/python bench/extract.py [--data ../shared/data/sun3d_studyroom]

Median over every frame of both SUN3D robots: GIST time, MSER+SIFT time, the whole frame
structure (GIST + features + BoW + back-projection) and encoded bytes, next to the
thesis's Table 2.1 and section 2.5.1 figures.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.extract import FrameExtractor
from fleetmap.features import detect_and_describe
from fleetmap.frame import encode
from fleetmap.gist import compute_gist
from fleetmap.vocabulary import load_vocabulary


def _ms(fn, *args) -> tuple[float, object]:
    t = time.perf_counter()
    out = fn(*args)
    return 1000 * (time.perf_counter() - t), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    root = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", type=Path, default=root.parent / "shared/data/sun3d_studyroom")
    args = ap.parse_args()
    vocab = load_vocabulary()
    extractor = FrameExtractor(vocab)
    rows = []
    for robot in ("robot_a", "robot_b"):
        rec = read_recording(args.data / robot)
        for fr in rec.frames:
            rgb, depth = load_rgb(fr.rgb_path), load_depth(fr.depth_path)
            t_gist, _ = _ms(compute_gist, rgb, vocab.gist_params)
            t_local, lf = _ms(detect_and_describe, rgb)
            t_all, frame = _ms(extractor, robot, fr.stamp, rgb, depth, rec.intrinsics, fr.T_map_cam)
            rows.append((t_gist, t_local, t_all, len(encode(frame)), frame.n_features))
    a = np.array(rows)
    n_feat = float(np.median(a[:, 4]))
    thesis_bytes = 1536 + 512 * n_feat
    print(f"frames: {len(a)} (640x480, SUN3D), features per frame: median {n_feat:.0f}")
    print("| quantity | fleetmap (median) | thesis |")
    print("|---|---|---|")
    print(f"| GIST | {np.median(a[:, 0]):.2f} ms | 90 ms (C, Table 2.1) |")
    print(f"| MSER + SIFT | {np.median(a[:, 1]):.1f} ms | 680 ms (SIFT, OpenCV, Table 2.1) |")
    print(
        f"| whole frame structure | {np.median(a[:, 2]):.1f} ms (p90 "
        f"{np.percentile(a[:, 2], 90):.1f}) | 770 ms |"
    )
    print(
        f"| encoded frame | {np.median(a[:, 3]) / 1024:.1f} KiB | "
        f"{thesis_bytes / 1024:.1f} KiB at {n_feat:.0f} features (1,536 B + 512 B/feature) |"
    )
    print(f"| ratio to thesis bytes | {np.median(a[:, 3]) / thesis_bytes:.3f} | 1 |")


if __name__ == "__main__":
    main()
