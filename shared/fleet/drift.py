"""A visual-inertial odometry drift model, injected into a recording's own poses.

VIO observes gravity, so its rotation drifts only about the gravity axis (yaw), and its
translation drifts in scale. Model (issue 22): along the path, the yaw error after a
distance d is theta(d) = b d + sigma W(d), with b = +-rate (deg/m, sign drawn per robot)
and W a Wiener process with sigma = rate / 2 deg per sqrt(m); each step's translation is
scaled by (1 + s), s = +-scale (1 %, sign drawn per robot). Every camera keeps its true
relative motion up to these small errors, so keyframes stay locally right while the map
bends. Gravity is taken as the mean of the cameras' image-down axes (cameras are held
upright), so no dataset's axis convention is assumed.
"""

from __future__ import annotations

import numpy as np


def up_axis(poses: np.ndarray) -> np.ndarray:
    """Unit "up" in the map frame: minus the mean image-down axis of camera-to-map poses
    of shape (N, 4, 4)."""
    down = poses[:, :3, 1].mean(0)
    return -down / np.linalg.norm(down)


def _rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def inject_drift(
    poses: np.ndarray, rate_deg_per_m: float, scale: float = 0.01, seed: int = 0
) -> np.ndarray:
    """Drifted camera-to-map poses of shape (N, 4, 4) from true ones of the same shape,
    in time order; the first pose is kept."""
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"Expected poses of shape (N, 4, 4), got {poses.shape}")
    rng = np.random.default_rng(seed)
    up = up_axis(poses)
    bias = np.deg2rad(rate_deg_per_m) * rng.choice((-1.0, 1.0))
    sigma = np.deg2rad(rate_deg_per_m) / 2.0
    s = scale * rng.choice((-1.0, 1.0))
    out = poses.copy()
    theta, pos = 0.0, poses[0, :3, 3].copy()
    for i in range(1, len(poses)):
        step = poses[i, :3, 3] - poses[i - 1, :3, 3]
        d = float(np.linalg.norm(step))
        theta += bias * d + sigma * np.sqrt(d) * rng.standard_normal()
        R = _rot_about(up, theta)
        pos = pos + (1.0 + s) * R @ step
        out[i, :3, :3] = R @ poses[i, :3, :3]
        out[i, :3, 3] = pos
    return out


def write_drifted(
    src,
    dst,
    rate_deg_per_m: float,
    scale: float = 0.01,
    seed: int = 0,
    frames: slice = slice(None),
    T_new_old: np.ndarray | None = None,
) -> np.ndarray:
    """A robot folder at `dst` of the TUM robot folder `src`'s associated frames[frames],
    its poses (the robot's own SLAM) moved into a new map frame by T_new_old and drifted
    as `inject_drift` says; images hard-linked (copied where links fail). Returns the true
    camera-to-map poses of shape (N, 4, 4) in the new frame, in the copy's frame order."""
    from pathlib import Path

    from fleetmap.dataset import link_or_copy, read_recording
    from fleetmap.geometry import pose_to_tum

    src, dst = Path(src), Path(dst)
    kept = [f for f in read_recording(src).frames[frames] if f.T_map_cam is not None]
    M = np.eye(4) if T_new_old is None else T_new_old
    truth = np.stack([M @ f.T_map_cam for f in kept])
    drifted = inject_drift(truth, rate_deg_per_m, scale, seed)
    for sub in ("rgb", "depth"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    if (src / "camera.json").exists():
        (dst / "camera.json").write_text((src / "camera.json").read_text())
    rows: dict[str, list[str]] = {"rgb": [], "depth": [], "groundtruth": []}
    for f, T in zip(kept, drifted, strict=True):
        for sub, path in (("rgb", f.rgb_path), ("depth", f.depth_path)):
            target = dst / sub / path.name
            if not target.exists():
                link_or_copy(path, target)
            rows[sub].append(f"{f.stamp:.6f} {sub}/{path.name}")
        rows["groundtruth"].append(f"{f.stamp:.6f} " + " ".join(f"{x:.9f}" for x in pose_to_tum(T)))
    for name, lines in rows.items():
        (dst / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return truth
