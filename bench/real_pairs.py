"""Every real multi-frame pair in ../shared/data, `fleetmap merge` beside the map_merge_3d
recipe, on accuracy and time.

    .venv/bin/python bench/real_pairs.py [--data ../shared/data] [--seeds 3] [--only NAME ...]

Cases (robots cut from the real recordings by frame range, each cut moved into its own
random map frame; the true transforms follow from the recordings' poses and T_a_b.txt):

- sun3d: the SUN3D study room's two robots (wide baseline, self-similar cubicles);
- hololens: the HoloLens lounge's two robots (the walk revisits the kitchen);
- hololens3: three robots, hl_a cut in two with a short shared stretch, plus hl_b;
- hololens_far: the first 60 frames of hl_a (the corridor) against the last 60 of hl_b: little
  or no true overlap, where "unmerged" is a right answer;
- rpy_long: TUM fr1_rpy's even frames and its odd ones (a Kinect swung over one desk for 24 s,
  two robots of 120 frames, no image in both): robots that revisit one place at nearly every
  keyframe.

Per robot merged into the reference: mean displacement of its fused map points against the
truth (what a merged map shows), translation/rotation error, and whether it merged; the
end-to-end wall time of `fleetmap merge` (a subprocess, start-up included). The recipe: every
10th frame of each robot fused at 5 cm, FPFH + RANSAC + point-to-plane ICP (Open3D), three
seeds, for each robot against the reference; its time per pair. `true overlap` is the share
of the robot's fused map within 5 cm of the reference's under the true transform.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetmap.align import fpfh_ransac_icp  # noqa: E402
from fleetmap.dataset import cut_recording, read_recording  # noqa: E402
from fleetmap.fleet.view_choice import load_view  # noqa: E402
from fleetmap.geometry import apply, transform_error  # noqa: E402
from fleetmap.lazy import LazyModule  # noqa: E402
from fleetmap.mapcloud import views_cloud  # noqa: E402

o3d = LazyModule("open3d")

DATA = ROOT.parent / "shared" / "data"


def random_frame(rng: np.random.Generator) -> np.ndarray:
    """A random rigid map frame: T_new_old."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


def cases(data: Path) -> dict[str, list[tuple[str, Path, slice, np.ndarray]]]:
    """name -> robots as (name, source folder, frame range, T_source_srcmap) where the
    source map is a common frame per case (A's for two-folder sets)."""
    sun, hl = data / "sun3d_studyroom", data / "hololens_lounge"
    out = {}
    if sun.exists():
        T = np.loadtxt(sun / "T_a_b.txt")
        out["sun3d"] = [
            ("A", sun / "robot_a", slice(None), np.eye(4)),
            ("B", sun / "robot_b", slice(None), T),
        ]
    if hl.exists():
        T = np.loadtxt(hl / "T_a_b.txt")
        a, b = hl / "hl_a", hl / "hl_b"
        out["hololens"] = [("A", a, slice(None), np.eye(4)), ("B", b, slice(None), T)]
        out["hololens3"] = [
            ("A", a, slice(0, 110), np.eye(4)),
            ("B", a, slice(90, None), np.eye(4)),
            ("C", b, slice(None), T),
        ]
        out["hololens_far"] = [("A", a, slice(0, 60), np.eye(4)), ("B", b, slice(-60, None), T)]
    if sun.exists() and hl.exists():  # two buildings: any merge is wrong
        out["no_common_place"] = [
            ("A", hl / "hl_a", slice(None), np.eye(4)),
            ("B", sun / "robot_b", slice(None), None),
        ]
    rpy = data / "tum_fr1_rpy"
    if rpy.exists():  # last: the cases before it keep their random map frames
        out["rpy_long"] = [
            ("A", rpy, slice(0, None, 2), np.eye(4)),
            ("B", rpy, slice(1, None, 2), np.eye(4)),
        ]
    return out


def sweep_cases(data: Path) -> dict:
    """Windows of one robot's frames against windows of the other's (SUN3D: 25 frames every
    12, HoloLens: 60 every 40): many overlaps, from none to most (`--sweep`)."""
    out = {}
    for name, folder, a, b, length, step in (
        ("sun3d", data / "sun3d_studyroom", "robot_a", "robot_b", 25, 12),
        ("hololens", data / "hololens_lounge", "hl_a", "hl_b", 60, 40),
    ):
        if not folder.exists():
            continue
        T = np.loadtxt(folder / "T_a_b.txt")
        n_a, n_b = len(read_recording(folder / a)), len(read_recording(folder / b))
        win = min(length, n_a, n_b)
        for i in range(0, n_a - win + 1, step):
            for j in range(0, n_b - win + 1, step):
                out[f"{name}_a{i}_b{j}"] = [
                    ("A", folder / a, slice(i, i + win), np.eye(4)),
                    ("B", folder / b, slice(j, j + win), T),
                ]
    return out


def every_nth_views(robot_dir: Path, n: int = 10):
    rec = read_recording(robot_dir)
    return [load_view(rec, i) for i in range(0, len(rec), n)]


def run_case(name: str, robots, work: Path, seeds: int, rng) -> list[dict]:
    frames = {}  # robot -> T_robotmap_common
    dirs = []
    for rname, src, sl, T_common_src in robots:
        M = random_frame(rng)  # robot map <- source map
        d = work / name / rname
        cut_recording(src, sl, d, M)
        frames[rname] = None if T_common_src is None else M @ np.linalg.inv(T_common_src)
        dirs.append(f"{rname}={d}")
    out = work / f"{name}-out"
    t = time.perf_counter()
    proc = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "fleetmap"), "merge", *dirs, "--out", str(out)],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: merge failed: {proc.stderr[-2000:]}")
    report = json.loads((out / "report.json").read_text())
    ref = robots[0][0]
    clouds = {
        r: views_cloud(every_nth_views(work / name / r, 5), voxel=0.05, with_color=False)
        for r, *_ in robots
    }
    rows = []
    for rname, *_ in robots[1:]:
        pb = np.asarray(clouds[rname].points)
        row = {"case": name, "robot": f"{ref}<-{rname}", "wall_s": wall}
        row |= {"timing": report["timing_s"], "true_overlap": 0.0}
        T = report["transforms"].get(rname)
        if frames[rname] is None:  # no common place: a merge is wrong, the recipe not run
            rows.append(row | {"merged": T is not None, "wrong": T is not None, "recipe": []})
            continue
        T_true = frames[ref] @ np.linalg.inv(frames[rname])
        tree = o3d.geometry.KDTreeFlann(clouds[ref])
        moved = apply(T_true, pb)
        near = sum(tree.search_knn_vector_3d(p, 1)[2][0] < 0.05**2 for p in moved[::5])
        row["true_overlap"] = near / len(moved[::5])
        if T is not None:
            T = np.array(T)
            dt, dr = transform_error(T, T_true)
            row |= {"merged": True, "mean_cm": 100 * _mean_disp(T, T_true, pb), "dt": dt, "dr": dr}
        else:
            row |= {"merged": False}
        va, vb = every_nth_views(work / name / ref), every_nth_views(work / name / rname)
        recipe = []
        for seed in range(seeds):
            t = time.perf_counter()
            Tr, _ = fpfh_ransac_icp(va, vb, seed=seed)
            recipe.append((100 * _mean_disp(Tr, T_true, pb), time.perf_counter() - t))
        row["recipe"] = recipe
        rows.append(row)
    return rows


def _mean_disp(T, T_true, pts) -> float:
    return float(np.linalg.norm(apply(T, pts) - apply(T_true, pts), axis=1).mean())


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--only", nargs="*", help="case names to run")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random map frames")
    ap.add_argument(
        "--sweep",
        action="store_true",
        help="instead of the cases, 60-frame windows of A against windows of B (no recipe)",
    )
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    all_cases = sweep_cases(args.data) if args.sweep else cases(args.data)
    if args.sweep:
        args.seeds = 0
    if not all_cases:
        sys.exit(f"real_pairs.py: no recordings under {args.data}")
    print(
        "| case | robots | true overlap | fleetmap: merged, mean map-point error, t / R error | "
        "fleetmap end to end | recipe mean error (3 seeds) | recipe time per pair |"
    )
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="fleetmap-real-") as tmp:
        for name, robots in all_cases.items():
            if args.only and name not in args.only:
                continue
            for r in run_case(name, robots, Path(tmp), args.seeds, rng):
                if r.get("wrong") is not None:
                    ours = "**yes: a wrong merge**" if r["wrong"] else "no (right: no common place)"
                elif r["merged"]:
                    ours = f"yes, {r['mean_cm']:.1f} cm, {100 * r['dt']:.1f} cm / {r['dr']:.2f} deg"
                else:
                    ours = "no"
                rec = ", ".join(f"{e:.1f}" for e, _ in r["recipe"]) or "-"
                rt = np.mean([t for _, t in r["recipe"]]) if r["recipe"] else float("nan")
                print(
                    f"| {r['case']} | {r['robot']} | {100 * r['true_overlap']:.0f}% | {ours} | "
                    f"{r['wall_s']:.1f} s | {rec} cm | {rt:.1f} s |",
                    flush=True,
                )
                print(f"<!-- {r['case']} {r['robot']} stages: {r['timing']} -->", flush=True)


if __name__ == "__main__":
    main()
