"""A simulated fleet end to end: `fleetmap simulate` then `fleetmap merge`, accuracy and time.

    .venv/bin/python bench/fleet.py [--robots 8] [--frames 200] [--workdir DIR]

Every rendered frame is made a keyframe (--kf-interval 0), so each robot brings `frames`
keyframes. Prints per-robot error against the true transforms and report.json's timing.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from fleetmap.geometry import transform_error
from fleetmap.services.cli import main as cli


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--workdir", type=Path, default=None)
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="fleetmap-fleet-"))
    sim, out = work / "fleet", work / "out"
    t = time.perf_counter()
    if not (sim / "T_true.json").is_file():  # reuse a fleet already rendered in --workdir
        cli(["simulate", str(sim), "--robots", str(args.robots), "--frames", str(args.frames)])
    t_sim = time.perf_counter() - t
    truth = json.loads((sim / "T_true.json").read_text())
    t = time.perf_counter()
    cli(
        [
            "merge",
            *(str(sim / r) for r in truth),
            "--out",
            str(out),
            "--kf-interval",
            "0",
            "--kf-translation",
            "0",
            "--kf-rotation",
            "0",
        ]
    )
    t_merge = time.perf_counter() - t
    report = json.loads((out / "report.json").read_text())
    print(
        f"\nsimulated {args.robots} robots x {args.frames} frames in {t_sim:.0f} s; "
        f"merge {t_merge:.0f} s; unmerged: {report['unmerged']}"
    )
    print("| robot | keyframes | translation error | rotation error |")
    print("|---|---|---|---|")
    for robot, T in report["transforms"].items():
        dt, dr = transform_error(np.array(T), np.array(truth[robot]))
        print(
            f"| {robot} | {report['robots'][robot]['keyframes']} | {100 * dt:.2f} cm | "
            f"{dr:.3f} deg |"
        )
    print(
        f"\ntiming_s: {report['timing_s']}; verified overlaps: {len(report['overlaps'])}; "
        f"pose graph: {report['pose_graph']}"
    )


if __name__ == "__main__":
    main()
