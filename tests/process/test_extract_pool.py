"""Keyframes extracted on every core: the same frames as one process, in the same order,
with each keyframe's map-cloud share where its depth puts it."""

from __future__ import annotations

import numpy as np

from fleetmap.camera import depth_to_points
from fleetmap.dataset import load_depth, read_recording
from fleetmap.extract import keyframe_indices
from fleetmap.extract_pool import CLOUD_STRIDE, extract_keyframes
from fleetmap.frame import encode
from fleetmap.geometry import apply


def test_workers_give_the_frames_one_process_gives(sun3d):
    recs = [read_recording(sun3d / "robot_a", "A"), read_recording(sun3d / "robot_b", "B")]
    kf = {r.robot_id: keyframe_indices(r)[:5] for r in recs}
    pooled = list(extract_keyframes(recs, kf, workers=2))
    single = list(extract_keyframes(recs, kf, workers=1))
    assert [(k.robot_id, k.index) for k in pooled] == [
        (r.robot_id, i) for r in recs for i in kf[r.robot_id]
    ]
    for p, s in zip(pooled, single, strict=True):
        assert encode(p.frame) == encode(s.frame)
        np.testing.assert_array_equal(p.points, s.points)
    # the cloud share: every CLOUD_STRIDE-th depth pixel, in the robot's map frame
    k = pooled[0]
    f = recs[0].frames[k.index]
    p, _ = depth_to_points(load_depth(f.depth_path), recs[0].intrinsics, stride=CLOUD_STRIDE)
    near = p[:, 2] < 6.0
    np.testing.assert_allclose(k.points, apply(f.T_map_cam, p[near]), atol=1e-4)
    assert k.colours.dtype == np.uint8 and k.colours.shape == k.points.shape


def test_closing_the_iterator_stops_the_workers(sun3d):
    rec = read_recording(sun3d / "robot_a", "A")
    it = extract_keyframes([rec], {"A": keyframe_indices(rec)}, workers=2)
    first = next(it)
    it.close()  # no hang, no leftover work
    assert first.robot_id == "A"


def test_workers_start_from_a_folder_holding_a_fleetmap_folder(tmp_path):
    """Run from the clone's parent (a `fleetmap` folder in the working folder), the fork
    server imported that folder as the package and every worker failed ("Cannot read
    vocabulary <cwd>/fleetmap/assets/...", BrokenProcessPool); the workers now import the
    installed package wherever the command runs."""
    import subprocess
    import sys
    from pathlib import Path

    robot = Path(__file__).parents[2] / "examples" / "fr1_rpy_fleet" / "alpha"
    script = tmp_path / "run.py"
    script.write_text(
        "import sys\n"
        "from fleetmap.dataset import read_recording\n"
        "from fleetmap.extract_pool import extract_keyframes\n"
        f"rec = read_recording({str(robot)!r}, 'A')\n"
        "kfs = list(extract_keyframes([rec], {'A': list(range(len(rec)))}, workers=2))\n"
        "print(len(kfs), len(rec))\n"
    )
    cwd = tmp_path / "parent"
    (cwd / "fleetmap" / "assets").mkdir(parents=True)  # a clone's name, or an --out folder
    run = subprocess.run(
        [sys.executable, str(script)], cwd=cwd, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-2000:]
    n, total = map(int, run.stdout.split())
    assert n == total >= 8  # enough frames for the process pool
