"""Reading a robot's recording in the TUM RGB-D layout (see CONTRACT.md section 1)."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fleetmap.camera import TUM_FR1, Intrinsics, no_reading_as_0
from fleetmap.errors import BadInput, BadRobotData
from fleetmap.tum_lists import MAX_POSE_INTERVAL_S, associate, poses_at, read_list, read_poses
from fleetmap.view import check_intrinsics

log = logging.getLogger(__name__)

#: Colour, depth and pose are associated by nearest timestamp within this many seconds.
MAX_ASSOCIATION_GAP_S = 0.02
_NEAR = (
    f"within {MAX_ASSOCIATION_GAP_S} s; a pose also between two at most {MAX_POSE_INTERVAL_S} "
    "s apart"
)

#: The working resolution: a recording whose images hold more pixels is read downscaled to
#: this many (aspect kept; colour area-averaged, depth nearest so no edge gets mixed depths;
#: intrinsics scaled with it). Every length in pixels (MSER areas, the epipolar RANSAC's
#: 2 px, the clouds' pixel stride, the aligner's pixel budget of 2 x 12 views) was set on
#: 512x384-640x480 sensors; a 1280x720 camera read at full size sent 1080x720 views past
#: the aligner's budget (the merge stopped: "send fewer or smaller views") and extracted at
#: a quarter of the speed. 3 cm voxels at 2-3 m are 5-10 pixels here: nothing the fit uses
#: is lost.
WORK_PIXELS = 640 * 480


@dataclass(frozen=True)
class FrameRecord:
    """One associated RGB-D frame of a recording (images are read lazily)."""

    stamp: float
    rgb_path: Path
    depth_path: Path | None
    T_map_cam: np.ndarray | None  # (4, 4) camera-to-map, or None without ground truth


@dataclass
class Recording:
    """A robot folder: its id, intrinsics and associated frames in time order.

    `intrinsics` are those of the images as `rgb` and `depth` load them: the files' own
    (`file_intrinsics`) unless they hold more than `WORK_PIXELS`, then downscaled."""

    robot_id: str
    root: Path
    intrinsics: Intrinsics
    frames: list[FrameRecord] = field(default_factory=list)
    file_intrinsics: Intrinsics | None = None  # None: the same as `intrinsics`
    source: Path | None = None  # what was given where it is not `root`: a ROS bag

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def reader(self) -> ImageReader:
        return ImageReader(self.intrinsics, self.file_intrinsics)

    def rgb(self, f: FrameRecord) -> np.ndarray:
        """Frame f's colour image at the working resolution, uint8 (H, W, 3) BGR."""
        return self.reader.rgb(f.rgb_path)

    def depth(self, f: FrameRecord) -> np.ndarray:
        """Frame f's depth image at the working resolution, uint16 (H, W)."""
        if f.depth_path is None:
            raise BadRobotData(f"{self.robot_id}: frame {f.stamp} has no depth")
        return self.reader.depth(f.depth_path)


@dataclass(frozen=True)
class ImageReader:
    """Loads a recording's images at its working resolution (`intrinsics`): resized from
    files of `file_intrinsics`' size, or as they are where that is None."""

    intrinsics: Intrinsics
    file_intrinsics: Intrinsics | None = None

    def rgb(self, path: Path) -> np.ndarray:
        return self._fit(load_rgb(path), cv2.INTER_AREA, path)

    def depth(self, path: Path) -> np.ndarray:
        return self._fit(load_depth(path), cv2.INTER_NEAREST, path)

    def _fit(self, img: np.ndarray, interpolation: int, path: Path) -> np.ndarray:
        src, k = self.file_intrinsics or self.intrinsics, self.intrinsics
        if img.shape[:2] != (src.height, src.width):  # named here, not as a shape later
            raise BadRobotData(
                f"{path}: {img.shape[1]}x{img.shape[0]}, the recording's first colour image "
                f"is {src.width}x{src.height}"
            )
        if self.file_intrinsics is None:
            return img
        return cv2.resize(img, (k.width, k.height), interpolation=interpolation)


def working_intrinsics(native: Intrinsics) -> Intrinsics | None:
    """The intrinsics at the working resolution for images of `native`'s size, or None
    where they are read at their own size (`WORK_PIXELS`)."""
    w, h = native.width, native.height
    if w * h <= WORK_PIXELS:
        return None
    s = (WORK_PIXELS / (w * h)) ** 0.5
    return native.resized(max(1, int(w * s)), max(1, int(h * s)))


def _named(root: Path, vals: list[str]) -> Path:
    """The file a list line's fields after its time name (`_resolve`): the first field, or
    all of them where that is the file there is (a name with spaces, which the TUM layout's
    columns split: "Cannot read colour image .../robot A/color: no such file")."""
    if not vals:
        raise BadRobotData(f"{root}: a list line with a time but no file name")
    name = vals[0]
    if len(vals) > 1 and not (root / name).exists() and (root / " ".join(vals)).exists():
        name = " ".join(vals)
    return _resolve(root, name)


def _resolve(root: Path, name: str) -> Path:
    p = (root / name).resolve()
    if not p.is_relative_to(root.resolve()):
        raise BadRobotData(
            f"{root}: list entry {name!r} points outside the robot folder (resolved, links "
            f"followed: {p}); copy the file in, or link the whole folder"
        )
    return p


def read_recording(
    root: str | Path,
    robot_id: str | None = None,
    intrinsics: Intrinsics | None = None,
    require_depth: bool = False,
    require_poses: bool = False,
    topics=None,
) -> Recording:
    """Read a robot folder in the TUM layout.

    Colour frames are kept only where a depth frame (and a pose, if `groundtruth.txt`
    exists) lies within `MAX_ASSOCIATION_GAP_S`. Intrinsics come from `intrinsics`, else
    `camera.json`, else the TUM fr1 defaults. `root` may also be a ROS bag
    (`fleetmap.bags`; `topics`: a `BagTopics` where message types are ambiguous).
    """
    root = Path(root)
    from fleetmap.bags import is_bag, read_bag

    if is_bag(root):  # a ROS bag: read as the TUM folder it converts to (cached)
        return read_bag(root, robot_id, intrinsics, require_depth, require_poses, topics)
    if not root.is_dir():
        if root.exists():  # a file: not "not found"
            raise BadRobotData(f"{root} is a file, not a robot folder nor a ROS bag")
        raise BadRobotData(f"Robot folder not found: {root}")
    robot_id = robot_id or default_robot_id(root)
    cam = root / "camera.json"
    origin = "given" if intrinsics is not None else (cam if cam.is_file() else None)
    if intrinsics is None:
        intrinsics = Intrinsics.from_json_file(cam) if origin else TUM_FR1
    rgb = read_list(root / "rgb.txt")
    if not rgb:
        raise BadRobotData(f"{root / 'rgb.txt'} lists no frames")
    has_depth = (root / "depth.txt").is_file()
    if require_depth and not has_depth:
        raise BadRobotData(f"Missing file: {root / 'depth.txt'}")
    near = float(np.median([r[0] for r in rgb]))  # the clock the other lists are read in
    depth = read_list(root / "depth.txt", near) if has_depth else None
    pose_t, poses = _poses(root / "groundtruth.txt", require_poses, near)

    frames = _associated(root, rgb, depth, pose_t, poses)
    if not frames:
        raise BadRobotData(f"{root}: no colour frame has depth and a pose ({_NEAR})")
    dropped = len(rgb) - len(frames)  # TUM's association: no frame left out unsaid
    twice = len(rgb) - len({r[0] for r in rgb})  # one depth and pose for the first only
    why = f"{dropped} without depth or a pose within {MAX_ASSOCIATION_GAP_S} s" + (
        f", {twice} of them at a stamp listed before" if twice else "")  # fmt: skip
    (log.warning if dropped else log.info)(
        "%s: %d associated frames of %d colour images%s", robot_id, len(frames), len(rgb),
        f" ({why})" * bool(dropped),
    )  # fmt: skip
    native = _of_images(intrinsics, frames[0].rgb_path, origin, root)
    work = working_intrinsics(native)
    if work is None:
        return Recording(robot_id, root, native, frames)
    n = native
    log.info("%s: %dx%d images read at %dx%d", robot_id, n.width, n.height, work.width, work.height)
    return Recording(robot_id, root, work, frames, file_intrinsics=native)


def default_robot_id(root: Path) -> str:
    """The robot id of a folder or bag given without a name: the folder's name, the bag's
    stem."""
    from fleetmap.bags import is_bag

    return Path(root).resolve().stem if is_bag(root) else Path(root).resolve().name


def _poses(gt: Path, required: bool, near: float | None = None) -> tuple[np.ndarray, list]:
    """groundtruth.txt's times and poses; none where the file is absent and not `required`.
    A file given that lists no pose (empty, comments only) is named, not read as none."""
    if not gt.is_file():
        if required:
            raise BadRobotData(f"Missing file: {gt}")
        return np.array([]), []
    pose_t, poses = read_poses(gt, near)
    if not poses:
        raise BadRobotData(f"{gt} lists no poses ('timestamp tx ty tz qx qy qz qw' lines)")
    return pose_t, poses


def _of_images(intrinsics: Intrinsics, first: Path, origin, root: Path) -> Intrinsics:
    """The intrinsics at the size the images have (`first`, the first colour image).
    `origin`: the camera.json they came from, which must be for that size (a focal length
    and centre are one image size's) and plausible for it (`view.check_intrinsics`: a focal
    length in millimetres, a centre off the image); None: the TUM fr1 defaults, as the
    contract has them where there is no camera.json, with a warning where the images are
    not their 640x480; "given": the caller's, taken as they are (the CLI's flags check
    their own). `root`: the robot's folder, as the warnings name it."""
    h, w = load_rgb(first).shape[:2]
    if origin is None and (w, h) == (intrinsics.width, intrinsics.height):
        k = intrinsics  # said: a SUN3D folder without it read its millimetres as 1/5000 m
        log.warning(
            "%s: no camera.json: the TUM fr1 defaults taken (fx %.1f fy %.1f cx %.1f cy %.1f, "
            "%g depth units per metre); for another camera give camera.json or --fx --fy "
            "--cx --cy --depth-scale", root, k.fx, k.fy, k.cx, k.cy, k.depth_scale,
        )  # fmt: skip
    elif origin is None:
        log.warning(
            "%s is %dx%d, and there is no camera.json: the TUM fr1 defaults taken in its place "
            "are a 640x480 camera's, so the map's geometry will be off; give camera.json or "
            "--fx --fy --cx --cy --depth-scale", first, w, h,
        )  # fmt: skip
    elif origin not in (None, "given"):
        if (w, h) != (intrinsics.width, intrinsics.height):
            raise BadRobotData(
                f"{origin} is for {intrinsics.width}x{intrinsics.height} images, but "
                f"{first} is {w}x{h}"
            )
        try:
            check_intrinsics(intrinsics, w, h, str(origin))
        except BadInput as exc:
            raise BadRobotData(str(exc)) from None
    return dataclasses.replace(intrinsics, width=w, height=h)


def _associated(root: Path, rgb: list, depth: list | None, pose_t, poses) -> list[FrameRecord]:
    """Colour frames with their depth frame (where the folder has depth) within
    MAX_ASSOCIATION_GAP_S, and pose (where it has poses: `tum_lists.poses_at`)."""
    rgb_t = np.array([r[0] for r in rgb])
    d_of = (
        {}
        if depth is None
        else dict(associate(rgb_t, np.array([r[0] for r in depth]), MAX_ASSOCIATION_GAP_S))
    )
    p_of = poses_at(rgb_t, pose_t, poses, MAX_ASSOCIATION_GAP_S) if len(poses) else {}
    frames = []
    for i, (stamp, vals) in enumerate(rgb):
        if depth is not None and i not in d_of or len(poses) and i not in p_of:
            continue
        if not vals:
            raise BadRobotData(f"{root / 'rgb.txt'}: no file name at t={stamp}")
        frames.append(
            FrameRecord(
                stamp=stamp,
                rgb_path=_named(root, vals),
                depth_path=None if depth is None else _named(root, depth[d_of[i]][1]),
                T_map_cam=p_of[i] if len(poses) else None,
            )
        )
    return frames


def load_rgb(path: Path) -> np.ndarray:
    """Colour image as uint8 (H, W, 3) BGR; raises BadRobotData if missing or unreadable."""
    if not Path(path).is_file():  # before OpenCV, which prints its own warning
        raise BadRobotData(f"Cannot read colour image {path}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadRobotData(f"Cannot read colour image {path}")
    with open(path, "rb") as f:  # a JPEG without its end marker: imread fills it with grey
        head = f.read(2)
        f.seek(max(0, Path(path).stat().st_size - 64))
        if head == b"\xff\xd8" and not f.read().rstrip(b"\x00").endswith(b"\xff\xd9"):
            raise BadRobotData(f"Colour image {path} is cut short (a JPEG without its end)")
    return img


def load_depth(path: Path) -> np.ndarray:
    """Depth image as uint16 (H, W), 0 where there is no reading (`camera.no_reading_as_0`);
    raises BadRobotData if missing, unreadable or not 16-bit."""
    if not Path(path).is_file():  # before OpenCV, which prints its own warning
        raise BadRobotData(f"Cannot read depth image {path}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise BadRobotData(f"Cannot read depth image {path}")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise BadRobotData(
            f"Depth image {path} must be 16-bit single-channel, got {img.dtype} {img.shape}"
            + " (metres as floats: write round(metres x 1000) as 16-bit PNG, depth_scale 1000)"
            * (img.dtype.kind == "f")
        )
    return no_reading_as_0(img)


def cut_recording(
    src: Path,
    frames: slice,
    dst: Path,
    T_new_old: np.ndarray,
    scale: float = 1.0,
    depth_noise: float = 0.0,
) -> Path:
    """A robot folder at `dst` holding `src`'s frames[frames], their poses moved into
    another map frame (T_new_old maps src's map into the new one): a robot made from part
    of a recording, for benchmarks, tests and demos. Images are hard-linked where the file
    system allows (the reader refuses symlinks leaving the folder), else copied.

    `scale`: the scene as if `scale` times its size, seen from `scale` times as near (the
    depths, through camera.json's depth_scale, and the new map frame's lengths x scale; the
    images as they are): how the pipeline meets a desk or a hall with the same data and its
    truth (a transform between two such robots: its translation x scale).

    `depth_noise`: an active-stereo camera's depth error at 1 m (metres RMS, growing as the
    square of the depth: `simulate.stereo_depth_noise`, at the scaled depths) added to every
    depth image, which is then written, not linked: the same scene seen by a noisier
    sensor (`simulate.D435_SIGMA_1M`), on top of the recording's own noise. Seeded by the
    frame's index in `src`, so a frame is the same in every cut."""
    import json

    from fleetmap.geometry import pose_to_tum

    if not scale > 0:
        raise ValueError(f"scale must be positive, not {scale}")
    if not 0 <= depth_noise < 1:  # NaN and inf are not
        raise ValueError(f"depth_noise must be 0 to under 1 metre at 1 m, not {depth_noise}")
    rec = read_recording(src)
    native = rec.file_intrinsics or rec.intrinsics
    for sub in ("rgb", "depth"):
        (dst / sub).mkdir(parents=True)
    if scale != 1.0:
        cam = native.to_dict()
        cam["depth_scale"] /= scale
        (dst / "camera.json").write_text(json.dumps(cam))
    elif (src / "camera.json").exists():
        (dst / "camera.json").write_text((src / "camera.json").read_text())
    rows: dict[str, list[str]] = {"rgb": [], "depth": [], "groundtruth": []}
    for i, f in zip(range(len(rec.frames))[frames], rec.frames[frames], strict=True):
        for sub, path in (("rgb", f.rgb_path), ("depth", f.depth_path)):
            if sub == "depth" and depth_noise > 0:
                _noisy_depth(path, dst / sub / path.name, native.depth_scale, scale, depth_noise, i)
            else:
                link_or_copy(path, dst / sub / path.name)
            rows[sub].append(f"{f.stamp:.6f} {sub}/{path.name}")
        T = T_new_old @ f.T_map_cam
        T[:3, 3] *= scale
        pose = " ".join(f"{x:.9f}" for x in pose_to_tum(T))
        rows["groundtruth"].append(f"{f.stamp:.6f} {pose}")
    for name, lines in rows.items():
        (dst / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return dst


def link_or_copy(src: Path, dst: Path) -> None:
    """A hard link to `src` at `dst` where the file system allows, else a copy."""
    import os
    import shutil

    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _noisy_depth(src: Path, dst: Path, ds: float, scale: float, sigma_1m: float, seed: int):
    """`cut_recording`'s depth image with an active-stereo camera's noise at the scaled
    depths (`simulate.stereo_depth_noise`), written in the source's units."""
    from fleetmap.simulate import stereo_depth_noise

    raw = load_depth(src)
    z = scale * raw.astype(np.float64) / ds  # metres in the scaled scene
    noisy = stereo_depth_noise(z, sigma_1m, np.random.default_rng(seed))
    out = np.clip(np.round(noisy / scale * ds), 0, 65535).astype(np.uint16)
    if not cv2.imwrite(str(dst), out):
        raise OSError(f"cannot write {dst}")
