"""A synthetic fleet recording: a procedurally textured room rendered as RGB-D.

For demos, CI and scale tests where no real data may be shipped. The room is an
axis-aligned box with furniture boxes inside; every face carries its own random texture
(blobs, boxes, lines, on a coloured ground) so MSER and SIFT find real, unique structure.
Each robot walks an arc around the room centre looking outward, with the robots' arcs
overlapping; each robot's poses are written in its own random map frame, and the true
transforms between map frames are written beside (`T_true.json`). Rendering is vectorised
ray casting (slab tests against every box), about 0.1 s per 640x480 frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fleetmap.camera import Intrinsics
from fleetmap.geometry import invert, pose_to_tum


def texture(rng: np.random.Generator, size: int = 256, shapes: int = 60) -> np.ndarray:
    """A random texture of shape (size, size, 3) uint8 with blob, box and line structure."""
    img = np.empty((size, size, 3), np.uint8)
    img[:] = rng.integers(40, 215, 3)
    for _ in range(shapes):
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(4, 28)), colour, -1)
        elif kind == 1:
            w, h = (int(v) for v in rng.integers(6, 60, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), colour, -1)
        else:
            x2, y2 = (int(v) for v in rng.integers(0, size, 2))
            cv2.line(img, (x, y), (x2, y2), colour, int(rng.integers(1, 5)))
    return cv2.GaussianBlur(img, (3, 3), 0)


@dataclass
class Box:
    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)
    inside: bool  # True for the room (rays start inside and hit its walls from within)
    textures: list[np.ndarray]  # one per face: -x, +x, -y, +y, -z, +z


class Scene:
    """A room (x, y on the floor, z up, metres) with furniture boxes."""

    def __init__(self, seed: int = 0, size=(8.0, 6.0, 3.0), n_boxes: int = 6):
        rng = np.random.default_rng(seed)
        self.boxes = [
            Box(np.zeros(3), np.array(size), True, [texture(rng, 1024, 500) for _ in range(6)])
        ]
        for _ in range(n_boxes):
            dims = rng.uniform([0.4, 0.4, 0.5], [1.2, 1.2, 1.6])
            lo = np.array(
                [
                    rng.uniform(0.3, size[0] - dims[0] - 0.3),
                    rng.uniform(0.3, size[1] - dims[1] - 0.3),
                    0.0,
                ]
            )
            centre = np.array(size[:2]) / 2
            if np.linalg.norm(lo[:2] + dims[:2] / 2 - centre) < 1.6:  # keep the middle free
                continue
            self.boxes.append(Box(lo, lo + dims, False, [texture(rng) for _ in range(6)]))
        self.size = np.array(size)

    def render(self, T_world_cam: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 BGR and depth (H, W) uint16 seen from a camera pose."""
        h, w = intr.height, intr.width
        v, u = np.mgrid[0:h, 0:w]
        d_cam = np.stack(
            [(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones((h, w))], -1
        ).reshape(-1, 3)
        R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
        d = d_cam @ R.T
        best_t = np.full(len(d), np.inf)
        best_face = np.full(len(d), -1)
        best_box = np.full(len(d), -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            for k, box in enumerate(self.boxes):
                t1, t2 = (box.lo - o) * inv, (box.hi - o) * inv
                if box.inside:  # exit point of the room
                    t_far = np.where(d > 0, t2, t1)
                    t = np.min(t_far, axis=1)
                    axis = np.argmin(t_far, axis=1)
                    face = 2 * axis + (np.take_along_axis(d, axis[:, None], 1)[:, 0] > 0)
                else:  # entry point of a solid box
                    t_near = np.minimum(t1, t2)
                    t_exit = np.min(np.maximum(t1, t2), axis=1)
                    t = np.max(t_near, axis=1)
                    axis = np.argmax(t_near, axis=1)
                    face = 2 * axis + (np.take_along_axis(d, axis[:, None], 1)[:, 0] < 0)
                    t = np.where((t <= t_exit) & (t > 1e-6), t, np.inf)
                hit = t < best_t
                best_t[hit], best_face[hit], best_box[hit] = t[hit], face[hit], k
        p = o + d * best_t[:, None]
        colour = np.zeros((len(d), 3), np.uint8)
        for k, box in enumerate(self.boxes):
            for f in range(6):
                sel = (best_box == k) & (best_face == f)
                if not sel.any():
                    continue
                a, b = [ax for ax in range(3) if ax != f // 2]
                tex = box.textures[f]
                # one texture stretched over the whole face: nothing repeats
                ext = box.hi - box.lo
                tu = ((p[sel, a] - box.lo[a]) / ext[a] * tex.shape[1]).astype(int)
                tv = ((p[sel, b] - box.lo[b]) / ext[b] * tex.shape[0]).astype(int)
                tu = np.clip(tu, 0, tex.shape[1] - 1)
                tv = np.clip(tv, 0, tex.shape[0] - 1)
                colour[sel] = tex[tv, tu]
        z = (best_t * d_cam[:, 2]).reshape(h, w)
        depth = np.where(np.isfinite(z), np.round(z * intr.depth_scale), 0)
        depth = np.clip(depth, 0, 65535).astype(np.uint16)
        return colour.reshape(h, w, 3), depth


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV camera: x right, y down, z forward) looking at target,
    z of the world up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def robot_poses(scene: Scene, k: int, n_robots: int, frames: int) -> list[np.ndarray]:
    """Robot k's camera poses: an arc around the room centre, looking outward, overlapping
    the arcs of robots k-1 and k+1."""
    centre = np.array([*scene.size[:2] / 2, 1.2])
    span = 2 * np.pi / n_robots * 1.6
    start = 2 * np.pi * k / n_robots
    poses = []
    for i in range(frames):
        a = start + span * i / max(frames - 1, 1)
        eye = centre + np.array([0.6 * np.cos(a), 0.6 * np.sin(a), 0.0])
        target = centre + np.array([3.0 * np.cos(a + 0.25), 3.0 * np.sin(a + 0.25), -0.3])
        poses.append(look_at(eye, target))
    return poses


def random_frame(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-20, 20, 3)
    return T


def simulate_fleet(
    out: Path,
    n_robots: int = 3,
    frames: int = 30,
    seed: int = 0,
    intr: Intrinsics | None = None,
    progress=lambda x, **k: x,
) -> dict:
    """Write n_robots robot folders (TUM layout) under out; returns the true transforms
    {robot: T_robot0map_robotmap} (also written to out/T_true.json)."""
    intr = intr or Intrinsics(fx=400.0, fy=400.0, cx=320.0, cy=240.0, depth_scale=5000.0)
    scene = Scene(seed)
    rng = np.random.default_rng(seed + 1)
    maps = [np.eye(4)] + [random_frame(rng) for _ in range(n_robots - 1)]  # T_map_world
    names = [f"robot{k}" for k in range(n_robots)]
    for k, name in enumerate(names):
        root = out / name
        (root / "rgb").mkdir(parents=True, exist_ok=True)
        (root / "depth").mkdir(exist_ok=True)
        rows_rgb, rows_d, rows_gt = [], [], []
        poses = robot_poses(scene, k, n_robots, frames)
        for i, T_world_cam in enumerate(progress(poses, desc=f"render {name}", unit="frame")):
            stamp = 1000.0 * (k + 1) + 0.1 * i
            rgb, depth = scene.render(T_world_cam, intr)
            cv2.imwrite(str(root / "rgb" / f"{stamp:.6f}.png"), rgb)
            cv2.imwrite(str(root / "depth" / f"{stamp:.6f}.png"), depth)
            rows_rgb.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
            rows_d.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
            pose = maps[k] @ T_world_cam
            rows_gt.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(pose)))
        (root / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rows_rgb) + "\n")
        (root / "depth.txt").write_text("# timestamp filename\n" + "\n".join(rows_d) + "\n")
        (root / "groundtruth.txt").write_text(
            "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows_gt) + "\n"
        )
        (root / "camera.json").write_text(json.dumps(intr.to_dict()))
    truth = {name: (maps[0] @ invert(maps[k])).tolist() for k, name in enumerate(names)}
    (out / "T_true.json").write_text(json.dumps(truth, indent=1))
    return truth


#: An active-stereo camera's depth error at 1 m (metres, RMS): Intel's D435 at 848x480
#: (focal about 430 px, baseline 50 mm, subpixel disparity error about 0.08 px: Intel's
#: "Tuning depth cameras for best performance", RMS error = z^2 x subpixel / (focal x
#: baseline)), 3.7 mm at 1 m, 15 mm at 2 m. Kinect v1 is 1.4 mm at 1 m (Khoshelham and
#: Elberink 2012), the recordings' own sensors about that.
D435_SIGMA_1M = 0.0037


def stereo_depth_noise(
    depth_m: np.ndarray, sigma_1m: float, rng: np.random.Generator, block_px: int = 8
) -> np.ndarray:
    """`depth_m` (H, W, metres, 0 = no reading) as an active-stereo camera would measure it:
    depth comes from disparity (z = f b / d), so a disparity error of constant spread is a
    depth error growing as z^2 (RMS `sigma_1m` x z^2). Stereo matching correlates a patch, so
    neighbouring pixels err together: half the variance is a smooth field over blocks of
    `block_px` pixels (bilinear), half is each pixel's own. No reading stays none."""
    h, w = depth_m.shape
    coarse = rng.standard_normal((h // block_px + 2, w // block_px + 2)).astype(np.float32)
    smooth = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
    # a bilinear field of unit-variance nodes has less than unit variance: rescale it
    smooth /= max(float(smooth.std()), 1e-6)
    eps = (smooth + rng.standard_normal((h, w)).astype(np.float32)) / np.sqrt(2.0)
    noisy = depth_m + sigma_1m * depth_m**2 * eps
    return np.where((depth_m > 0) & (noisy > 0), noisy, 0.0)


def other_camera(folder: Path, rows: float = 0.75, factor: float = 1.325) -> Path:
    """A robot folder (as `dataset.cut_recording` writes it) as another camera would have
    recorded it: the central `rows` share of every image's rows (a narrower vertical field
    of view; 0.75 makes 4:3 images 16:9), resized by `factor` (colour by area or cubic,
    depth nearest), and camera.json's intrinsics moved with them (640 x 480 -> 848 x 477 at
    the defaults). For fleets of mixed sensors in benchmarks and tests. Images are written
    anew: a hard link into the source recording is removed first, never written through."""
    from fleetmap.dataset import read_recording

    if not (0 < rows <= 1 and factor > 0):
        raise ValueError(f"rows in (0, 1] and a positive factor, not {rows}, {factor}")
    rec = read_recording(folder)
    native = rec.file_intrinsics or rec.intrinsics
    top = int(round(native.height * (1 - rows) / 2))
    bottom = native.height - top
    w, h = round(native.width * factor), round((bottom - top) * factor)
    cropped = replace(native, cy=native.cy - top, height=bottom - top)
    cam = cropped.resized(w, h).to_dict()
    for sub in ("rgb", "depth"):
        for p in sorted((folder / sub).iterdir()):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[top:bottom]
            how = cv2.INTER_CUBIC if factor > 1 else cv2.INTER_AREA
            how = cv2.INTER_NEAREST if sub == "depth" else how
            _write_anew(p, cv2.resize(img, (w, h), interpolation=how))
    (folder / "camera.json").write_text(json.dumps(cam))
    return folder


#: A camera's other colour response, for `other_exposure`: a gamma on the normalised
#: levels and a white balance (red, green, blue gains) beside its exposure gain.
OTHER_GAMMA, OTHER_WHITE = 0.8, (1.1, 1.0, 0.85)


def other_exposure(
    folder: Path, gain: float, gamma: float = OTHER_GAMMA, white=OTHER_WHITE
) -> Path:
    """A robot folder (as `dataset.cut_recording` writes it) as a camera of another exposure
    and colour response would have recorded it: every colour level (0..1) raised to
    `gamma`, times `gain` and each channel's `white` gain (red, green, blue), clipped to
    the 8 bits (a `gain` over 1 saturates the highlights, under 1 crushes the shadows
    into fewer levels). Robots whose cameras expose differently (auto-exposure facing a
    window or a dark corner, another model's gamma and white balance), for benchmarks and
    tests; the depth untouched. Images are written anew, in their own format: a hard link
    into the source recording is removed first, never written through."""
    if not (gain > 0 and gamma > 0 and len(white) == 3 and all(w > 0 for w in white)):
        raise ValueError(
            f"a positive gain, gamma and three white gains, not {gain}, {gamma}, {white}"
        )
    bgr = np.asarray(white[::-1], np.float64) * gain  # OpenCV's channel order
    levels = (np.arange(256) / 255.0) ** gamma
    lut = np.clip(np.round(255 * levels[:, None] * bgr[None, :]), 0, 255).astype(np.uint8)
    for p in sorted((folder / "rgb").iterdir()):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise OSError(f"cannot read {p}")
        out = np.stack([lut[img[..., c], c] for c in range(3)], axis=-1)
        _write_anew(p, out)
    return folder


def _write_anew(path: Path, img: np.ndarray) -> None:
    """`img` written to `path` as a new file: a hard link into the source recording
    (`dataset.cut_recording`'s) is removed first, never written through."""
    path.unlink()
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot write {path}")
