"""Drift injected into real recordings: the fleet graph's merged trajectories against the
rigid floor, today's rigid placement and the map_merge_3d recipe (issue 22).

    .venv/bin/python bench/drift.py [--cases hololens hololens3 hololens_short hololens_long sun3d
        rpy rpy_long] [--rates 0 0.25 0.5 1] [--seeds 2] [--recipe] [--timing] [--json rows.json]
        [--keep DIR]

Drift model (`fleetmap.fleet.drift`): each robot's own poses get a yaw error about gravity
growing with the distance walked (bias +-rate deg/m, random walk rate/2 deg/sqrt(m)) and
a 1 % scale error on each step (none at rate 0); the images are untouched. Each robot has
its own draw (seed * 10 + robot index).

ATE: RMSE of the camera positions of every frame of every robot, after one rigid alignment
(Umeyama/Kabsch without scale, `fleetmap.registration.kabsch`: the formula of evo's
`evo_ape --align`) of the whole fleet to the truth in the reference robot's frame:
- fleetmap: `fleetmap merge`'s trajectories/*.txt (drift-corrected where applied);
- rigid placement: each robot's drifted poses under its rigid placement before correction
  (what fleetmap wrote before issue 22);
- rigid floor: each robot's drifted trajectory aligned rigidly to its truth on its own
  (the best any rigid placement can do), pooled over the robots;
- recipe: the drifted trajectories under the map_merge_3d recipe's transforms (every 10th
  view fused, FPFH + RANSAC + ICP, seed 0).
Each row also gives every robot's RMSE under fleetmap's one alignment (`fleetmap_by_robot`)
and the pairs' fits (`fits`); `--keep DIR` keeps every merge's robots and output.
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

from fleetmap.dataset import read_recording  # noqa: E402
from fleetmap.fleet.drift import write_drifted  # noqa: E402
from fleetmap.registration import kabsch  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
# `cases`' names
CASES = ("hololens", "hololens3", "hololens_short", "hololens_long", "sun3d", "rpy", "rpy_long")


def cases(data: Path) -> dict:
    """name -> robots as (name, source folder, frame range, T_common_source)."""
    hl, sun, rpy = data / "hololens_lounge", data / "sun3d_studyroom", data / "tum_fr1_rpy"
    out = {}
    if hl.exists():
        T = np.loadtxt(hl / "T_a_b.txt")
        a, b = hl / "hl_a", hl / "hl_b"
        out["hololens"] = [("A", a, slice(None), np.eye(4)), ("B", b, slice(None), T)]
        out["hololens3"] = [
            ("A", a, slice(None), np.eye(4)),
            ("B", b, slice(0, 100), T),
            ("C", b, slice(90, None), T),
        ]
        # the kitchen scale: two robots of about 4 m of path each sharing 35-50 % of
        # their maps (A's 4.3 m through the lounge, B's first 3.6 m)
        out["hololens_short"] = [("A", a, slice(30, 75), np.eye(4)), ("B", b, slice(0, 45), T)]
        # hl_a's even frames and its odd ones: 15 m walked twice side by side, a closure at
        # most keyframe pairs (about 250): many closures and a map that drift bends
        out["hololens_long"] = [
            ("A", a, slice(0, None, 2), np.eye(4)),
            ("B", a, slice(1, None, 2), np.eye(4)),
        ]
    if sun.exists():
        T = np.loadtxt(sun / "T_a_b.txt")
        out["sun3d"] = [
            ("A", sun / "robot_a", slice(None), np.eye(4)),
            ("B", sun / "robot_b", slice(None), T),
        ]
    if rpy.exists():
        out["rpy"] = [("A", rpy, slice(0, 125), np.eye(4)), ("B", rpy, slice(115, None), np.eye(4))]
        # the even frames and the odd ones: long robots over one desk, a closure at nearly
        # every keyframe pair
        out["rpy_long"] = [
            ("A", rpy, slice(0, None, 2), np.eye(4)),
            ("B", rpy, slice(1, None, 2), np.eye(4)),
        ]
    return out


def read_tum(path: Path) -> dict[float, np.ndarray]:
    """stamp -> position (3,) of a TUM trajectory file."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    return {round(r[0], 6): r[1:4] for r in rows}


def _sq(e: np.ndarray, t: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Squared distances (m^2) of positions e moved by T to their truths t."""
    return (((e @ T[:3, :3].T + T[:3, 3]) - t) ** 2).sum(1)


def ate(est: list[np.ndarray], truth: list[np.ndarray]) -> float:
    """RMSE (m) after one rigid alignment of all the estimated positions to the truth."""
    e, t = np.concatenate(est), np.concatenate(truth)
    return float(np.sqrt(_sq(e, t, kabsch(e, t)).mean()))


def ate_by_robot(est: list[np.ndarray], truth: list[np.ndarray]) -> list[float]:
    """Each robot's RMSE (m) under `ate`'s one alignment of the whole fleet: which robot
    the pooled figure comes from."""
    T = kabsch(np.concatenate(est), np.concatenate(truth))
    return [float(np.sqrt(_sq(e, t, T).mean())) for e, t in zip(est, truth, strict=True)]


def floor(drifted: list[np.ndarray], truth: list[np.ndarray]) -> float:
    """Pooled RMSE with each robot aligned on its own."""
    sq = [_sq(e, t, kabsch(e, t)) for e, t in zip(drifted, truth, strict=True)]
    return float(np.sqrt(np.concatenate(sq).mean()))


def recipe_transform(dir_ref: Path, dir_r: Path) -> np.ndarray:
    from fleetmap.align import fpfh_ransac_icp
    from fleetmap.fleet.view_choice import load_view

    views = []
    for d in (dir_ref, dir_r):
        rec = read_recording(d)
        views.append([load_view(rec, i) for i in range(0, len(rec), 10)])
    return fpfh_ransac_icp(views[0], views[1], seed=0)[0]


def run(name: str, robots, rate: float, seed: int, work: Path, recipe: bool) -> dict:
    """One merge of the case's drifted robots; the four ATEs in cm."""
    dirs, truth, stamps = {}, {}, {}
    T_ref_common = np.linalg.inv(robots[0][3])
    for k, (r, src, sl, T_common_src) in enumerate(robots):
        d = work / f"{name}-{rate}-{seed}" / r
        scale = 0.01 if rate > 0 else 0.0
        true = write_drifted(src, d, rate, scale, seed * 10 + k, sl)
        truth[r] = np.stack([T_ref_common @ T_common_src @ T for T in true])[:, :3, 3]
        stamps[r] = [round(f.stamp, 6) for f in read_recording(d).frames]
        dirs[r] = d
    out = work / f"{name}-{rate}-{seed}-out"
    fm = str(ROOT / ".venv" / "bin" / "fleetmap")
    cmd = [fm, "-q", "merge", *(f"{r}={d}" for r, d in dirs.items()), "--out", str(out)]
    cmd.append("--correct-drift")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: merge failed: {proc.stderr[-2000:]}")
    report = json.loads((out / "report.json").read_text())
    merged = [r for r in dirs if r in report["transforms"]]
    drifted = {r: np.stack([f.T_map_cam for f in read_recording(dirs[r]).frames]) for r in dirs}
    est = [
        np.array([read_tum(out / "trajectories" / f"{r}.txt")[s] for s in stamps[r]])
        for r in merged
    ]
    tru = [truth[r] for r in merged]
    placed = {
        r: np.array(report["robots"][r]["drift_correction"]["rigid_placement"]) for r in merged
    }
    rigid = [(placed[r] @ drifted[r])[:, :3, 3] for r in merged]
    row = {"case": name, "rate": rate, "seed": seed, "merged": len(merged), "robots": len(dirs)}
    row |= {"fleetmap": ate(est, tru), "rigid_placement": ate(rigid, tru)}
    row["fleetmap_by_robot"] = dict(zip(merged, ate_by_robot(est, tru), strict=True))
    row |= {"floor": floor([drifted[r][:, :3, 3] for r in merged], tru)}
    row |= {"graph": report["fleet_graph"], "timing": report["timing_s"]}
    row["fits"] = [  # which pairs merged and how: what the graph started from
        {k: f.get(k) for k in ("robot_a", "robot_b", "merged", "method", "inliers", "reason")}
        for f in report["fits"]
    ]
    if recipe:
        rec = [drifted[merged[0]][:, :3, 3]] + [
            (recipe_transform(dirs[merged[0]], dirs[r]) @ drifted[r])[:, :3, 3] for r in merged[1:]
        ]
        row["recipe"] = ate(rec, tru)
    return row


def timing_2000(n_robots: int = 4, per_robot: int = 500, seed: int = 0) -> tuple[float, float]:
    """Seconds (wall, this process's CPU) to optimise a synthetic fleet of 2,000 keyframes:
    random walks with 5 cm steps, drifted, one closure every 10th keyframe to another
    robot's nearest keyframe."""
    from fleetmap.fleet.closures import Closure
    from fleetmap.fleet.drift import inject_drift
    from fleetmap.fleet.graph import optimise

    rng = np.random.default_rng(seed)
    truth, poses = {}, {}
    for k in range(n_robots):
        P = np.tile(np.eye(4), (per_robot, 1, 1))
        P[:, :3, 3] = np.cumsum(rng.normal(0, 0.03, (per_robot, 3)), 0) + rng.normal(0, 1, 3)
        P[:, :3, 1] = [0, 0, -1]  # image down = -z
        P[:, :3, 0], P[:, :3, 2] = [1, 0, 0], [0, 1, 0]
        truth[f"r{k}"], poses[f"r{k}"] = P, inject_drift(P, 1.0, 0.01, seed + k)
    closures = []
    names = list(truth)
    for k, r in enumerate(names):
        o = names[(k + 1) % len(names)]
        for i in range(0, per_robot, 10):
            j = int(np.linalg.norm(truth[o][:, :3, 3] - truth[r][i, :3, 3], axis=1).argmin())
            T = np.linalg.inv(truth[r][i]) @ truth[o][j]
            closures.append(Closure(r, i, o, j, T, 50))
    placed = {r: np.eye(4) for r in names}
    t, cpu = time.perf_counter(), time.process_time()
    optimise(poses, placed, closures, names[0])
    return time.perf_counter() - t, time.process_time() - cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--rates", nargs="*", type=float, default=[0, 0.25, 0.5, 1])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--recipe", action="store_true")
    ap.add_argument("--timing", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--keep", type=Path, help="keep every merge's drifted robots and output here (to inspect)"
    )
    args = ap.parse_args()
    if args.keep and args.keep.exists() and not args.keep.is_dir():
        ap.error(f"--keep {args.keep}: not a folder")
    if args.timing:
        for seed in range(3):
            wall, cpu = timing_2000(seed=seed)
            print(f"optimise 2,000 keyframes: {wall:.3f} s wall, {cpu:.3f} s CPU")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        for name, robots in cases(args.data).items():
            if name not in args.cases:
                continue
            for rate in args.rates:
                for seed in range(args.seeds if rate > 0 else 1):
                    row = run(name, robots, rate, seed, work, args.recipe)
                    rows.append(row)
                    print(_line(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


def _line(r: dict) -> str:
    rec = f" recipe {100 * r['recipe']:.1f}" if "recipe" in r else ""
    g = r["graph"]
    return (
        f"{r['case']} {r['rate']} deg/m seed {r['seed']}: merged {r['merged']}/{r['robots']} "
        f"ATE cm fleetmap {100 * r['fleetmap']:.2f} rigid placement "
        f"{100 * r['rigid_placement']:.2f} floor {100 * r['floor']:.2f}{rec} | applied "
        f"{g['applied']} closures {g['closures']} intra {g['intra_robot']} rejected "
        f"{g['rejected']} optimise {g['optimise_s']} s | by robot "
        + " ".join(f"{k} {100 * v:.2f}" for k, v in r["fleetmap_by_robot"].items())
    )


if __name__ == "__main__":
    main()
