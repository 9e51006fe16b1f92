"""Shared fixtures: real data from ../shared/data (skipped cleanly where absent).

What is costly is built once per session and shared: the SUN3D pair's keyframes (as encoded
frames and as RGB-D views) and their alignment, the SUN3D merge, the simulated fleet, the
random textured fleet's frames and one aligner process. Tests must not change them."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.cpu_times import (  # noqa: F401 (the hooks: tests/cpu_times.py)
    pytest_addoption,
    pytest_runtest_logreport,
    pytest_runtest_makereport,
    pytest_runtest_setup,
    pytest_terminal_summary,
)
from tests.helpers import built_once
from tests.scheduling import (  # noqa: F401 (the hooks: tests/scheduling.py)
    pytest_collection_modifyitems,
    pytest_xdist_make_scheduler,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("FLEETMAP_DATA", ROOT.parent / "shared" / "data"))


def data_path(*parts: str) -> Path:
    """Path under the shared data folder, or skip the test where it is absent."""
    p = DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


@pytest.fixture(scope="session", autouse=True)
def _feature_cache(tmp_path_factory):
    """One features cache for the run (`fleetmap.feature_cache`), shared by its xdist workers
    and every process the tests start: a keyframe's image features are extracted the first
    time the suite meets its image (the same SUN3D and HoloLens frames are merged by many
    tests: whole recordings, windows, drifted copies) and read back after, bit for bit
    (tests/unit/test_feature_cache.py). Depth, poses and all the rest are computed each
    time. A run that names its own cache keeps it."""
    from fleetmap.feature_cache import ENV

    if os.environ.get(ENV):
        yield
        return
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # this run's folder, with the workers' own in it
    os.environ[ENV] = str(base / "feature-cache")
    yield
    os.environ.pop(ENV, None)


@pytest.fixture(scope="session")
def sun3d() -> Path:
    return data_path("sun3d_studyroom")


@pytest.fixture(scope="session")
def hololens() -> Path:
    return data_path("hololens_lounge")


@pytest.fixture(scope="session")
def tum_rpy() -> Path:
    return data_path("tum_fr1_rpy")


@pytest.fixture(scope="session")
def corridor() -> Path:
    return data_path("rtabmap_corridor")


@pytest.fixture(scope="session")
def tum_pairs() -> Path:
    return data_path("tum_fr1_xyz")


@pytest.fixture(scope="session")
def vocabulary():
    from fleetmap.vocabulary import load_vocabulary

    return load_vocabulary()


def read_tum_pose(path: Path) -> np.ndarray:
    from fleetmap.geometry import pose_from_tum

    v = np.array(path.read_text().split(), dtype=float)
    return pose_from_tum(v[:3], v[3:7])


@pytest.fixture
def tum_robot(tum_pairs: Path, tmp_path: Path) -> Path:
    """A two-frame robot folder in the TUM layout, without camera.json (fr1 defaults)."""
    root = tmp_path / "tum_robot"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    case = tum_pairs / "case_1"
    rows = {"rgb": [], "depth": [], "gt": []}
    for stamp, tag in ((1305031102.2159, "prev"), (1305031102.2758, "curr")):
        shutil.copy(case / f"img_{tag}.png", root / "rgb" / f"{stamp:.4f}.png")
        shutil.copy(case / f"dep_{tag}.png", root / "depth" / f"{stamp:.4f}.png")
        rows["rgb"].append(f"{stamp:.4f} rgb/{stamp:.4f}.png")
        rows["depth"].append(f"{stamp + 0.004:.4f} depth/{stamp:.4f}.png")
        rows["gt"].append(f"{stamp:.4f} " + (case / f"pose_{tag}.txt").read_text().strip())
    (root / "rgb.txt").write_text("# colour\n" + "\n".join(rows["rgb"]) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(rows["depth"]) + "\n")
    (root / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows["gt"]) + "\n"
    )
    return root


def imread(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def write_robot(
    root: Path, frames: list[tuple[float, Path, Path, np.ndarray]], camera: dict | None = None
) -> Path:
    """A robot folder in the TUM layout from (stamp, rgb file, depth file, T_map_cam)."""
    from fleetmap.geometry import pose_to_tum

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth, gt = [], [], []
    for stamp, rgb_src, depth_src, T in frames:
        shutil.copy(rgb_src, root / "rgb" / f"{stamp:.6f}.png")
        shutil.copy(depth_src, root / "depth" / f"{stamp:.6f}.png")
        rgb.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
        depth.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
        gt.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(T)))
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if camera is not None:
        import json

        (root / "camera.json").write_text(json.dumps(camera))
    return root


@pytest.fixture
def tum_robot_dirs(tum_pairs: Path, tmp_path: Path):
    """Two one-frame robots from TUM fr1 case_1; B's map frame is a random rigid one.
    Returns (dir A, dir B, T_a_b)."""
    from scipy.spatial.transform import Rotation

    case = tum_pairs / "case_1"
    T_b_w = np.eye(4)
    T_b_w[:3, :3] = Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    T_b_w[:3, 3] = [4.0, -2.5, 1.2]
    a = write_robot(
        tmp_path / "alpha",
        [
            (
                100.0,
                case / "img_prev.png",
                case / "dep_prev.png",
                read_tum_pose(case / "pose_prev.txt"),
            )
        ],
    )
    b = write_robot(
        tmp_path / "bravo",
        [
            (
                200.0,
                case / "img_curr.png",
                case / "dep_curr.png",
                T_b_w @ read_tum_pose(case / "pose_curr.txt"),
            )
        ],
    )
    return a, b, np.linalg.inv(T_b_w)


def textured_image(seed: int, h: int = 240, w: int = 320) -> np.ndarray:
    """A procedurally textured image with real MSER/SIFT structure (blobs, boxes, lines)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.full((h, w, 3), rng.integers(60, 200), np.uint8)
    for _ in range(60):
        colour = tuple(int(c) for c in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(3, 20)), colour, -1)
        elif kind == 1:
            cv2.rectangle(
                img,
                (x, y),
                (x + int(rng.integers(5, 40)), y + int(rng.integers(5, 40))),
                colour,
                -1,
            )
        else:
            cv2.line(img, (x, y), (int(rng.integers(0, w)), int(rng.integers(0, h))), colour, 2)
    return img


@pytest.fixture(scope="session")
def fleet_frames(vocabulary, tmp_path_factory):
    """8 robots x 25 encoded frames of distinct textured views: {robot: [bytes]} (9 s of CPU:
    extracted once per run, `built_once`)."""
    import pickle

    from fleetmap.extract import FrameExtractor
    from fleetmap.frame import encode

    def build(folder: Path) -> None:
        x = FrameExtractor(vocabulary)
        frames = {
            f"r{k}": [
                encode(x(f"r{k}", 100.0 + i, textured_image(1000 * k + i))) for i in range(25)
            ]
            for k in range(8)
        }
        (folder / "frames.pickle").write_bytes(pickle.dumps(frames))

    folder = built_once(tmp_path_factory, "fleet_frames", build)
    return pickle.loads((folder / "frames.pickle").read_bytes())


def random_frame(seed: int) -> np.ndarray:
    """A random rigid 4x4 transform, translation within 10 m."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-10, 10, 3)
    return T


@pytest.fixture
def tum_two_robots(tum_pairs):
    """TUM fr1 frames 60 ms apart as robots A and B; B's map frame is a random one."""
    from fleetmap.camera import TUM_FR1
    from fleetmap.correspondences import RGBDView

    case = tum_pairs / "case_1"
    T_b_w = random_frame(3)
    a = RGBDView(
        imread(case / "img_prev.png"),
        imread(case / "dep_prev.png"),
        TUM_FR1,
        read_tum_pose(case / "pose_prev.txt"),
    )
    b = RGBDView(
        imread(case / "img_curr.png"),
        imread(case / "dep_curr.png"),
        TUM_FR1,
        T_b_w @ read_tum_pose(case / "pose_curr.txt"),
    )
    return [(a, b)], np.linalg.inv(T_b_w)  # T_a_b: A's map is the mocap world


@pytest.fixture(scope="session")
def pg_cluster():
    """A real PostgreSQL server for the session (skipped only where PostgreSQL 15's
    binaries are absent; scripts/install.sh installs them)."""
    from tests import pg

    if not pg.available():
        pytest.skip(f"PostgreSQL binaries not found in {pg.PG_BIN}")
    cluster = pg.Cluster().start()
    yield cluster
    cluster.remove()


@pytest.fixture
def pg_url(pg_cluster) -> str:
    """A fresh, empty database on the session's PostgreSQL server."""
    return pg_cluster.database()


# --- built once per session -------------------------------------------------------------


@pytest.fixture(scope="session")
def sun3d_keyframes(sun3d, vocabulary) -> dict:
    """The SUN3D pair's keyframes as `fleetmap extract` makes them: {robot: [Frame]}."""
    from fleetmap.dataset import read_recording
    from fleetmap.extract import FrameExtractor, extract_recording

    x = FrameExtractor(vocabulary)
    return {
        r: list(extract_recording(read_recording(sun3d / r), x)) for r in ("robot_a", "robot_b")
    }


@pytest.fixture(scope="session")
def sun3d_frames(sun3d_keyframes) -> dict[str, list[bytes]]:
    """The SUN3D pair's keyframes encoded, as robots post them: {robot: [bytes]}."""
    from fleetmap.frame import encode

    return {r: [encode(f) for f in frames] for r, frames in sun3d_keyframes.items()}


@pytest.fixture(scope="session")
def sun3d_views(sun3d) -> dict:
    """The SUN3D pair's keyframes as RGB-D views: {robot: [RGBDView]}."""
    from fleetmap.correspondences import RGBDView
    from fleetmap.dataset import load_depth, load_rgb, read_recording
    from fleetmap.extract import keyframe_indices

    out = {}
    for robot in ("robot_a", "robot_b"):
        rec = read_recording(sun3d / robot)
        out[robot] = [
            RGBDView(
                load_rgb(f.rgb_path), load_depth(f.depth_path), rec.intrinsics, f.T_map_cam, f.stamp
            )
            for f in (rec.frames[i] for i in keyframe_indices(rec))
        ]
    return out


@pytest.fixture(scope="session")
def sun3d_alignment(sun3d_views):
    """`align_views` of every SUN3D keyframe pair (A x B): one real wide-baseline fit."""
    from fleetmap.align import align_views

    return align_views([(a, b) for a in sun3d_views["robot_a"] for b in sun3d_views["robot_b"]])


@pytest.fixture(scope="session")
def sun3d_merge(sun3d, tmp_path_factory) -> tuple[Path, dict]:
    """`fleetmap merge A=robot_a B=robot_b`: (output folder, report.json)."""
    import json

    from fleetmap.services.cli import main

    out = tmp_path_factory.mktemp("sun3d_merge")
    args = ["-q", "merge", f"A={sun3d / 'robot_a'}", f"B={sun3d / 'robot_b'}", "--out", str(out)]
    assert main(args) == 0
    return out, json.loads((out / "report.json").read_text())


@pytest.fixture(scope="session")
def sim_fleet(tmp_path_factory) -> tuple[Path, dict]:
    """`fleetmap simulate`: 3 robots of 12 frames, every pair overlapping; (folder, the true
    transforms {robot: T_robot0_robot})."""
    import json

    from fleetmap.services.cli import main

    def build(sim: Path) -> None:  # 13 s of CPU: once per run (`built_once`)
        assert main(["-q", "simulate", str(sim), "--robots", "3", "--frames", "12"]) == 0

    sim = built_once(tmp_path_factory, "sim_fleet", build)
    return sim, json.loads((sim / "T_true.json").read_text())


#: The session aligner's setting: no second look (ASIFT on refused pairs, 10-30 s each).
NO_SECOND_LOOK = {"FLEETMAP_ALIGNER_ALIGN__SECOND_LOOK": "false"}


@pytest.fixture(scope="session")
def aligner_url() -> str:
    """One aligner process for the session (or ALIGNER_URL, e.g. `docker compose up`'s).
    Stateless between requests: tests share it. For tests of the services' mechanics (the
    live map, chaos, the CLI over HTTP), whose assertions hold with or without the second
    look, so it is off (NO_SECOND_LOOK): the live map's early fits on one or a few overlaps
    are refused without it. Tests of recall, refusal and accuracy keep the default (their
    merges start their own aligner)."""
    from tests.servers import running

    with running("aligner", url_env="ALIGNER_URL", env=NO_SECOND_LOOK) as url:
        yield url


@pytest.fixture(scope="session")
def corridor_frames(corridor, vocabulary):
    """The RTAB-Map corridor's 84 images as frame structures, by image number (stamp)."""
    from fleetmap.extract import FrameExtractor

    x = FrameExtractor(vocabulary)
    return {
        i: x("corridor", float(i), cv2.imread(str(corridor / "images" / f"{i}.jpg")))
        for i in range(1, 85)
    }


def corridor_revisits(corridor) -> dict[int, set[int]]:
    """The corridor's ground truth: query image -> the images it revisits."""
    gt: dict[int, set[int]] = {}
    for line in (corridor / "gt_loop_pairs.csv").read_text().splitlines():
        if line and not line.startswith("#"):
            q, m = map(int, line.split(","))
            gt.setdefault(q, set()).add(m)
    return gt
