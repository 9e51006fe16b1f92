"""Experiment: per-pair hypotheses + geometric scoring on the SUN3D pair (next step for the
aligner, not yet in `shared/align.py`).

    .venv/bin/python bench/sun3d_hypotheses.py      # about 6 minutes

For every (robot A keyframe, robot B keyframe) pair: raw mutual SIFT matches (ratio 0.9, no
epipolar filter), lifted to 3D, a rigid RANSAC (10 cm) per pair giving one hypothesis with
at least 4 inliers. Each hypothesis is refined by point-to-plane ICP between the two
robots' fused keyframe clouds and scored by overlap (share of B's points within 6 cm of
A's), then by coloured ICP. Prints the best 15 with their error against T_a_b.txt.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import open3d as o3d

from shared.camera import backproject_pixels
from shared.correspondences import RGBDView, view_features
from shared.dataset import load_depth, load_rgb, read_recording
from shared.extract import keyframe_indices
from shared.geometry import apply, transform_error
from shared.mapcloud import icp, overlap_fitness, views_cloud
from shared.matching import match_descriptors
from shared.registration import ransac_rigid

REG = o3d.pipelines.registration
DATA = Path(__file__).resolve().parents[1].parent / "shared/data/sun3d_studyroom"


def views(robot: str) -> list[RGBDView]:
    rec = read_recording(DATA / robot)
    return [
        RGBDView(
            load_rgb(rec.frames[i].rgb_path),
            load_depth(rec.frames[i].depth_path),
            rec.intrinsics,
            rec.frames[i].T_map_cam,
        )
        for i in keyframe_indices(rec)
    ]


def main() -> None:
    T_gt = np.loadtxt(DATA / "T_a_b.txt")
    va, vb = views("robot_a"), views("robot_b")
    t = time.perf_counter()
    fa, fb = [view_features(v) for v in va], [view_features(v) for v in vb]
    hyps = []
    for i, a in enumerate(va):
        for j, b in enumerate(vb):
            ia, ib = match_descriptors(fa[i].descriptors, fb[j].descriptors, 0.9)
            pa, oka = backproject_pixels(fa[i].keypoints[ia], a.depth, a.intrinsics)
            pb, okb = backproject_pixels(fb[j].keypoints[ib], b.depth, b.intrinsics)
            ok = oka & okb
            if ok.sum() < 5:
                continue
            T, inl = ransac_rigid(apply(b.T_map_cam, pb[ok]), apply(a.T_map_cam, pa[ok]), 0.1)
            if inl.sum() >= 4:
                hyps.append((T, int(inl.sum()), i, j))
    print(f"{len(hyps)} hypotheses in {time.perf_counter() - t:.1f} s")
    ca, cb = views_cloud(va, voxel=0.03), views_cloud(vb, voxel=0.03)
    rows = []
    for T, n, i, j in hyps:
        Ti, _, _ = icp(cb, ca, T, distances=(0.15, 0.06, 0.03))
        fit = overlap_fitness(cb, ca, Ti, 0.06)
        c = REG.registration_colored_icp(
            cb,
            ca,
            0.04,
            Ti,
            REG.TransformationEstimationForColoredICP(),
            REG.ICPConvergenceCriteria(max_iteration=50),
        )
        rows.append(
            (fit, n, i, j, transform_error(Ti, T_gt), transform_error(c.transformation, T_gt))
        )
    rows.sort(key=lambda r: -r[0])
    for fit, n, i, j, e1, e2 in rows[:15]:
        print(
            f"overlap {fit:.3f} inliers {n} pair a{i}/b{j}: ICP {e1[0]:.2f} m {e1[1]:.1f} deg"
            f" | coloured ICP {e2[0]:.2f} m {e2[1]:.1f} deg"
        )
    print(f"total {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
