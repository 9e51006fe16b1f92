"""The live map's targets (issue 13): robots streamed at once, as fast as possible, into
`fleetmap serve place-db --aligner`; how long after the last keyframe every robot is placed,
and each robot's error against the truth beside a batch `fleetmap merge` of the same folders.

    .venv/bin/python bench/live_stream.py [--data ../shared/data] [--case hololens3] [--seed 0]

Cases are `bench/real_pairs.py`'s (robots cut from the real recordings, each moved into its
own random map frame); `--isolated` adds SUN3D's robot B (another building: it must stay
unmerged). Errors are the mean displacement of the robot's map points (every 5th frame)
under the found transform against the true one, in cm. Times: `stream` is the wall time of
`fleetmap stream --speed X` (default 0: extraction and upload as fast as possible, the
services working meanwhile; 1: recording speed); `placed after last kf` is from its end to
the first `GET /map` (polled every 0.2 s) with every robot that should merge placed;
`settled` is until the merge worker has had nothing to align for 10 s (refinements
included); `final placement` is the last change of the placement after the last keyframe
(nominated pairs that end refused move nothing).

Per robot (`robots`, issue 23), from `GET /map` polled every 0.5 s during the stream too:
`evidence_s`, when its first verified overlap with a robot it should merge with appeared
(seconds since the stream started; the keyframes' overlap detection included, their
extraction not); `placed_after_evidence_s`, from then to its first placement; `first_cm`,
the error of that first placement ("ref": it was the reference then) and `settled_cm`, the
last map's; `fits`, each placement it had, in time order, with its error.

`--profile DIR`: py-spy (`pip install py-spy`) samples the place database and the aligner
from the stream's start to the first map with every robot that should merge placed, and
writes each one's collapsed stacks (DIR/place-db.txt, DIR/aligner.txt, one thread per
stack root) and its hottest functions (DIR/*.top.txt).

Which code runs is the interpreter's: `/work/main/.venv/bin/python bench/live_stream.py`
measures the install of /work/main with this script.
"""

from __future__ import annotations

import argparse
import functools
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
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

FLEETMAP = str(Path(sys.executable).parent / "fleetmap")  # the interpreter's install


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


@functools.cache
def _points(robot_dir: Path) -> np.ndarray:
    return np.asarray(views_cloud(every_nth_views(robot_dir, 5), voxel=0.05).points)


def errors(transforms: dict, frames: dict, ref: str, work: Path) -> dict:
    out = {}
    for r, T in transforms.items():
        if r == ref:
            continue
        if frames[r] is None:
            out[r] = "WRONG MERGE"
            continue
        pts = _points(work / r)
        T_true = frames[ref] @ np.linalg.inv(frames[r])
        out[r] = round(100 * _mean_disp(np.array(T), T_true, pts), 2)
    return out


class Watch(threading.Thread):
    """`GET /map` every `poll_s` while the robots stream: when each robot first had a
    verified overlap with a robot it should merge with, and every placement it had
    (time, reference, T_ref_robot), times in seconds since `t0`."""

    def __init__(self, url: str, should_merge: set[str], t0: float, poll_s: float = 0.5):
        super().__init__(daemon=True)
        self.url, self.should, self.t0, self.poll_s = url, should_merge, t0, poll_s
        self.evidence: dict[str, float] = {}
        self.fits: dict[str, list] = {}
        self.pairs: dict[str, dict] = {}  # "A|B|attempts" -> the pair's state, when first seen
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            try:
                self.look(httpx.get(self.url + "/map", timeout=60).json())
            except httpx.HTTPError:
                pass
            self.done.wait(self.poll_s)

    def look(self, m: dict) -> None:
        now = time.monotonic() - self.t0
        for p in m.get("pairs", []):
            self.pairs.setdefault(f"{p['robot_a']}|{p['robot_b']}|{p['attempts']}", p | {"t": now})
        for e in m.get("overlaps", []):
            a, b = e["robot_a"], e["robot_b"]
            if e["pairs"] and {a, b} <= self.should:
                self.evidence.setdefault(a, now)
                self.evidence.setdefault(b, now)
        T = m.get("transforms", {})
        if len(T) < 2:
            return
        for r, T_r in T.items():
            seen = self.fits.setdefault(r, [])
            if not seen or seen[-1][1:] != (m["reference"], T_r):
                seen.append((now, m["reference"], T_r))


def robot_rows(watch: Watch, final: dict, frames: dict, work: Path) -> dict:
    """Per robot: evidence, first placement and its delay, errors of every placement."""
    out = {}
    for r in sorted(watch.should):
        fits = watch.fits.get(r, [])
        errs = ["ref" if ref == r else errors({r: T}, frames, ref, work)[r] for _, ref, T in fits]
        ev = watch.evidence.get(r)
        out[r] = {
            "evidence_s": None if ev is None else round(ev, 1),
            "placed_after_evidence_s": round(fits[0][0] - ev, 1) if fits and ev else None,
            "first_cm": errs[0] if errs else None,
            "settled_cm": errors(final["transforms"], frames, final["reference"], work).get(r),
            "fits": [[round(f[0], 1), f[1], e] for f, e in zip(fits, errs, strict=True)],
            "transforms": [f[2] for f in fits],  # T_ref_robot of each placement
        }
    return out


def start_profiles(out: Path | None, services: list[Service]) -> list[subprocess.Popen]:
    """py-spy recording each service (raw collapsed stacks with thread ids), or none."""
    if out is None:
        return []
    out.mkdir(parents=True, exist_ok=True)
    spy = str(Path(sys.executable).parent / "py-spy")
    return [
        subprocess.Popen(
            [spy, "record", "-r", "50", "-t", "-f", "raw", "-p", str(s.proc.pid)]
            + ["-o", str(out / f"{s.kind}.txt")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for s in services
    ]


def stop_profiles(spies: list[subprocess.Popen], out: Path | None) -> None:
    """Stop the recordings (py-spy writes on SIGINT) and summarise each: samples by the
    innermost fleetmap function and by any function on the stack (inclusive)."""
    for p in spies:
        p.send_signal(signal.SIGINT)
    for p in spies:
        p.wait(60)
    for f in sorted(out.glob("*.txt")) if spies else []:
        if f.name.endswith(".top.txt"):
            continue
        own, incl, total = Counter(), Counter(), 0
        for line in f.read_text().splitlines():
            stack, _, n = line.rpartition(" ")
            frames = stack.split(";")
            total += int(n)
            ours = [x for x in frames if "fleetmap" in x or "/shared/" in x or "/services/" in x]
            own[ours[-1] if ours else frames[-1]] += int(n)
            for x in set(frames):
                incl[x] += int(n)
        rows = [f"{total} samples (50/s, every thread)", "-- innermost project function:"]
        rows += [f"{n:7d} {100 * n / total:5.1f}% {x}" for x, n in own.most_common(25)]
        rows += ["-- on the stack (inclusive):"]
        rows += [f"{n:7d} {100 * n / total:5.1f}% {x}" for x, n in incl.most_common(40)]
        f.with_suffix(".top.txt").write_text("\n".join(rows) + "\n")


def live_run(
    dirs: list[str],
    should_merge: set[str],
    work: Path,
    speed: float = 0.0,
    profile: Path | None = None,
) -> dict:
    aligner = Service("aligner").start()
    db = Service("place-db", work / "db", args=["--aligner", aligner.url]).start()
    spies = start_profiles(profile, [db, aligner])
    try:
        t0 = time.monotonic()
        watch = Watch(db.url, should_merge, t0)
        watch.start()
        subprocess.run(
            [FLEETMAP, "-q", "stream", *dirs, "--place-db", db.url, "--speed", str(speed)],
            check=True,
        )
        t_last = time.monotonic()
        placed_at, last_change, attempts = None, t_last, None
        while time.monotonic() - last_change < 10 and time.monotonic() - t_last < 600:
            m = httpx.get(db.url + "/map", timeout=60).json()
            if placed_at is None and should_merge <= set(m["transforms"]):
                placed_at = time.monotonic()
                stop_profiles(spies, profile)
                spies = []
            key = [p["attempts"] for p in m["pairs"]]
            w = m["worker"]
            busy = w is None or w["aligning"] or w["due"] or not w.get("quiet")
            if key != attempts or busy:
                attempts, last_change = key, time.monotonic()
            time.sleep(0.2)
        watch.done.set()
        watch.join()
        watch.look(m)
        return {
            "map": m,
            "watch": watch,
            "stream_end_s": t_last - t0,
            "stream_s": t_last - t0,
            "placed_after_s": None if placed_at is None else placed_at - t_last,
            "settled_after_s": last_change - t_last,
        }
    finally:
        stop_profiles(spies, profile)
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
    ap.add_argument("--keep", type=Path, help="copy the robot folders and truth here")
    ap.add_argument("--speed", type=float, default=0.0, help="times recording speed (0: max)")
    ap.add_argument("--profile", type=Path, help="py-spy the services until first placement")
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
        live = live_run(dirs, should, work, args.speed, args.profile)
        m = live["map"]
        row = {
            "case": args.case + (" + isolated" if args.isolated else ""),
            "speed": args.speed,
            "stream_s": round(live["stream_s"], 1),
            "placed_after_last_kf_s": None
            if live["placed_after_s"] is None
            else round(live["placed_after_s"], 1),
            "settled_after_last_kf_s": round(live["settled_after_s"], 1),
            # the placement's last change (a robot's transform or the reference) after the
            # last keyframe: when the map an operator looks at stops moving
            "final_placement_after_last_kf_s": round(
                max((f[-1][0] for f in live["watch"].fits.values() if f), default=0.0)
                - live["stream_s"],
                1,
            ),
            "reference": m["reference"],  # the live map's own (most keyframes)
            "live_cm": errors(m["transforms"], frames, m["reference"], work),
            "unmerged": m["unmerged"],
            "alignments": sum(p["attempts"] for p in m["pairs"]),
            "robots": robot_rows(live["watch"], m, frames, work),
        }
        if not args.no_batch:
            b = batch_run(dirs, work)
            row["batch_cm"] = errors(b["report"]["transforms"], frames, ref, work)
            row["batch_wall_s"] = round(b["wall_s"], 1)
        if args.keep:  # the robot folders and truth, for a look at the fits afterwards
            import shutil

            shutil.copytree(
                work, args.keep, dirs_exist_ok=True, ignore=shutil.ignore_patterns("db")
            )
            truth = {r: None if T is None else T.tolist() for r, T in frames.items()}
            (args.keep / "frames.json").write_text(json.dumps(truth))
        placements = {r: v.pop("transforms") for r, v in row["robots"].items()}
        if args.keep:
            (args.keep / "placements.json").write_text(json.dumps(placements))
            (args.keep / "pairs.json").write_text(json.dumps(live["watch"].pairs, indent=1))
        print(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
