"""Cut the README's demo fleet from TUM RGB-D fr1_rpy (CC BY 4.0): three robots, each a
window of the sequence, bravo's and charlie's poses moved into map frames of their own.

    .venv/bin/python scripts/cut_fr1_rpy_fleet.py [--src ../shared/data/tum_fr1_rpy]
        [--out examples/fr1_rpy_fleet]

Colour JPEGs are copied as they are; depth PNGs are re-encoded losslessly (16-bit, PNG
compression 9, about half the size); poses are the mocap's nearest row. The three
windows (every second frame of the every-3rd-frame cut, 18 frames, 3.6 s each) come from
the beginning, the middle and the end of the recording: the camera keeps swinging back
over the same desk, so every two of them overlap.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
#: robot -> (first frame of the source's rgb.txt, number of frames, step)
WINDOWS = {"alpha": (30, 16, 2), "bravo": (100, 16, 2), "charlie": (160, 16, 2)}
#: each robot's map frame in the mocap's: (x, y, z rotation in degrees, shift in metres);
#: alpha keeps the mocap frame (the reference), the others get arbitrary ones
MOVES = {
    "alpha": ((0, 0, 0), (0, 0, 0)),
    "bravo": ((20, -35, 110), (4.0, -2.5, 1.2)),
    "charlie": ((-60, 15, -150), (-3.0, 1.5, 0.4)),
}


def _rows(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]


def _matrix(row: list[str]) -> np.ndarray:
    """A TUM row (t tx ty tz qx qy qz qw) as the 4x4 camera-to-world pose."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([float(x) for x in row[4:8]]).as_matrix()
    T[:3, 3] = [float(x) for x in row[1:4]]
    return T


def _tum(stamp: str, T: np.ndarray) -> str:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return stamp + " " + " ".join(f"{x:.6f}" for x in (*T[:3, 3], *q))


def T_world_map(robot: str) -> np.ndarray:
    """Robot's map frame in the mocap (world) frame: maps its map points into the world."""
    angles, shift = MOVES[robot]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    T[:3, 3] = shift
    return np.linalg.inv(T)  # the move maps world points into the robot's map frame


def cut_robot(src: Path, out: Path, robot: str) -> int:
    """One robot folder: its window's colour, depth and poses in its own map frame."""
    first, count, step = WINDOWS[robot]
    rgb, depth = _rows(src / "rgb.txt"), _rows(src / "depth.txt")
    gt = _rows(src / "groundtruth.txt")
    gt_t = np.array([float(r[0]) for r in gt])
    T_map_world = np.linalg.inv(T_world_map(robot))
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    lines = {"rgb": [], "depth": [], "gt": []}
    for i in range(first, first + count * step, step):
        (t_rgb, f_rgb), (t_d, f_d) = rgb[i], depth[i]
        shutil.copyfile(src / f_rgb, out / f_rgb)
        d = cv2.imread(str(src / f_d), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(out / f_d), d, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        lines["rgb"].append(f"{t_rgb} {f_rgb}")
        lines["depth"].append(f"{t_d} {f_d}")
        row = gt[int(np.argmin(np.abs(gt_t - float(t_rgb))))]
        lines["gt"].append(_tum(t_rgb, T_map_world @ _matrix(row)))
    head = f"# {robot}: TUM RGB-D fr1_rpy frames {first}..{first + (count - 1) * step}"
    for name, what in (("rgb", "filename"), ("depth", "filename"), ("gt", "tx ty tz qx qy qz qw")):
        text = [head, f"# timestamp {what}", *lines[name]]
        (out / f"{'groundtruth' if name == 'gt' else name}.txt").write_text("\n".join(text) + "\n")
    shutil.copyfile(src / "camera.json", out / "camera.json")
    return count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=ROOT.parent / "shared" / "data" / "tum_fr1_rpy")
    ap.add_argument("--out", type=Path, default=ROOT / "examples" / "fr1_rpy_fleet")
    args = ap.parse_args()
    if not (args.src / "rgb.txt").is_file():
        raise SystemExit(f"cut_fr1_rpy_fleet: no TUM folder at {args.src}")
    args.out.mkdir(parents=True, exist_ok=True)
    truth = {}
    for robot in WINDOWS:
        if (args.out / robot).exists():
            shutil.rmtree(args.out / robot)
        cut_robot(args.src, args.out / robot, robot)
        # T_alpha_R = T_alpha_world @ T_world_R, alpha's map frame being the world's
        truth[robot] = T_world_map(robot).tolist()
    # {R: T_alpha_R}, mapping R's map frame into alpha's (as `fleetmap simulate` writes it)
    (args.out / "T_true.json").write_text(json.dumps(truth, indent=1) + "\n")


if __name__ == "__main__":
    main()
