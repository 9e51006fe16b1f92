"""The real wide-baseline pair, side by side in one run: our default aligner against the
purely geometric recipe of ROS map_merge_3d (Open3D: fused depth clouds, FPFH, RANSAC,
point-to-plane ICP), ICP from identity, and the largest visual consensus alone.

    .venv/bin/python bench/sun3d_merge.py [--data ../shared/data/sun3d_studyroom] [--seeds 3]

Both robots' keyframes (the default keyframe policy), every A view paired with every B
view, as `fleetmap merge` sends them. Errors against T_a_b.txt two ways: the transform's own
(translation at B's map origin, about 5 m from the data, and rotation), and the mean
displacement of B's map points (what a merged map shows). The ground truth itself holds to
about 2-3 cm and 1.5 degrees (SOURCE.md).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fleetmap.align import METHODS, AlignParams, align_views, fpfh_ransac_icp
from fleetmap.correspondences import RGBDView
from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.extract import keyframe_indices
from fleetmap.geometry import apply, transform_error
from fleetmap.mapcloud import views_cloud

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "sun3d_studyroom"


def keyframes(root: Path) -> list[RGBDView]:
    rec = read_recording(root)
    return [
        RGBDView(
            load_rgb(f.rgb_path), load_depth(f.depth_path), rec.intrinsics, f.T_map_cam, f.stamp
        )
        for f in (rec.frames[i] for i in keyframe_indices(rec))
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--seeds", type=int, default=3, help="RANSAC seeds for the FPFH recipe")
    args = ap.parse_args()
    T_gt = np.loadtxt(args.data / "T_a_b.txt")
    va, vb = keyframes(args.data / "robot_a"), keyframes(args.data / "robot_b")
    pairs = [(a, b) for a in va for b in vb]
    pb = np.asarray(views_cloud(vb, voxel=0.05).points)
    print(f"{len(va)} x {len(vb)} keyframes, {len(pairs)} pairs\n")
    print("| method | merged | translation at origin | rotation | mean map-point error | time |")
    print("|---|---|---|---|---|---|")

    def row(name, merged, T, seconds, note=""):
        if T is None:
            print(f"| {name} | {merged} {note} | - | - | - | {seconds:.1f} s |")
            return
        dt, dr = transform_error(T, T_gt)
        dm = np.linalg.norm(apply(T, pb) - apply(T_gt, pb), axis=1).mean()
        print(
            f"| {name} | {merged} {note} | {100 * dt:.1f} cm | {dr:.2f} deg | "
            f"{100 * dm:.1f} cm | {seconds:.1f} s |"
        )

    t = time.perf_counter()
    r = align_views(pairs)
    row("fleetmap default", r.merged, r.T_a_b, time.perf_counter() - t, f"({r.reason})")
    for seed in range(args.seeds):
        t = time.perf_counter()
        T, fit = fpfh_ransac_icp(va, vb, seed=seed)
        row(f"map_merge_3d recipe, seed {seed}", "-", T, time.perf_counter() - t, f"fit {fit:.2f}")
    p = AlignParams()
    for m in ("icp", "rigid"):
        t = time.perf_counter()
        r = METHODS[m](pairs, p)
        row(m, "-", r.T_a_b, time.perf_counter() - t)


if __name__ == "__main__":
    main()
