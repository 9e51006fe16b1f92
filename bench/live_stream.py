"""The live map's targets (issue 13): robots streamed at once, as fast as possible, into
`fleetmap serve place-db --aligner`; how long after the last keyframe every robot is placed,
and each robot's error against the truth beside a batch `fleetmap merge` of the same folders.

    .venv/bin/python bench/live_stream.py [--data ../shared/data] [--case hololens3] [--seed 0]

Cases are `bench/real_pairs.py`'s (robots cut from the real recordings, each moved into its
own random map frame); `--isolated` adds SUN3D's robot B (another building: it must stay
unmerged). Errors are the mean displacement of the robot's map points (every 5th frame)
under the found transform against the true one, in cm. Times: `stream` is the wall time of
`fleetmap stream --speed 0` (extraction and upload, the services working meanwhile);
`placed after last kf` is from its end to the first `GET /map` (polled every 0.2 s) with
every robot that should merge placed; `settled` is until the merge worker has had nothing
to align for 10 s (refinements included).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from real_pairs import DATA, _mean_disp, cases, every_nth_views, random_frame  # noqa: E402

from fleetmap.dataset import cut_recording  # noqa: E402
from fleetmap.mapcloud import views_cloud  # noqa: E402
from tests.servers import Service  # noqa: E402

FLEETMAP = str(ROOT / ".venv" / "bin" / "fleetmap")


def prepare(case: list, work: Path, rng, isolated: bool, data: Path):
    """Robot folders and T_robotmap_common per robot (None: no common place)."""
    if isolated:
        case = case + [("D", data / "sun3d_studyroom" / "robot_b", slice(None), None)]
    dirs, frames = [], {}
    for name, src, sl, T_common_src in case:
        M = random_frame(rng)
        cut_recording(src, sl, work / name, M)
        frames[name] = None if T_common_src is None else M @ np.linalg.inv(T_common_src)
        dirs.append(f"{name}={work / name}")
    return dirs, frames


def errors(transforms: dict, frames: dict, ref: str, work: Path) -> dict:
    out = {}
    for r, T in transforms.items():
        if r == ref:
            continue
        if frames[r] is None:
            out[r] = "WRONG MERGE"
            continue
        pts = np.asarray(views_cloud(every_nth_views(work / r, 5), voxel=0.05).points)
        T_true = frames[ref] @ np.linalg.inv(frames[r])
        out[r] = round(100 * _mean_disp(np.array(T), T_true, pts), 2)
    return out


def live_run(dirs: list[str], should_merge: set[str], work: Path) -> dict:
    aligner = Service("aligner").start()
    db = Service("place-db", work / "db", args=["--aligner", aligner.url]).start()
    try:
        t0 = time.monotonic()
        subprocess.run(
            [FLEETMAP, "-q", "stream", *dirs, "--place-db", db.url, "--speed", "0"], check=True
        )
        t_last = time.monotonic()
        placed_at, last_change, attempts = None, t_last, None
        while time.monotonic() - last_change < 10 and time.monotonic() - t_last < 600:
            m = httpx.get(db.url + "/map", timeout=60).json()
            if placed_at is None and should_merge <= set(m["transforms"]):
                placed_at = time.monotonic()
            key = [p["attempts"] for p in m["pairs"]]
            w = m["worker"]
            busy = w is None or w["aligning"] or w["due"] or not w.get("quiet")
            if key != attempts or busy:
                attempts, last_change = key, time.monotonic()
            time.sleep(0.2)
        return {
            "map": m,
            "stream_s": t_last - t0,
            "placed_after_s": None if placed_at is None else placed_at - t_last,
            "settled_after_s": last_change - t_last,
        }
    finally:
        db.stop()
        aligner.stop()


def batch_run(dirs: list[str], work: Path) -> dict:
    t = time.monotonic()
    out = work / "batch"
    subprocess.run([FLEETMAP, "-q", "merge", *dirs, "--out", str(out)], check=True)
    report = json.loads((out / "report.json").read_text())
    return {"report": report, "wall_s": time.monotonic() - t}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--case", default="hololens3")
    ap.add_argument("--isolated", action="store_true", help="add a robot from another building")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-batch", action="store_true")
    args = ap.parse_args()
    all_cases = cases(args.data)
    if args.case not in all_cases:
        sys.exit(f"live_stream.py: case {args.case!r} needs recordings under {args.data}")
    with tempfile.TemporaryDirectory(prefix="fleetmap-live-") as tmp:
        work = Path(tmp)
        dirs, frames = prepare(
            all_cases[args.case], work, np.random.default_rng(args.seed), args.isolated, args.data
        )
        ref = dirs[0].split("=")[0]
        should = {r for r, T in frames.items() if T is not None}
        live = live_run(dirs, should, work)
        m = live["map"]
        row = {
            "case": args.case + (" + isolated" if args.isolated else ""),
            "stream_s": round(live["stream_s"], 1),
            "placed_after_last_kf_s": None
            if live["placed_after_s"] is None
            else round(live["placed_after_s"], 1),
            "settled_after_last_kf_s": round(live["settled_after_s"], 1),
            "reference": m["reference"],  # the live map's own (most keyframes)
            "live_cm": errors(m["transforms"], frames, m["reference"], work),
            "unmerged": m["unmerged"],
            "alignments": sum(p["attempts"] for p in m["pairs"]),
        }
        if not args.no_batch:
            b = batch_run(dirs, work)
            row["batch_cm"] = errors(b["report"]["transforms"], frames, ref, work)
            row["batch_wall_s"] = round(b["wall_s"], 1)
        print(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
