"""Shared fixtures: real data from ../shared/data (skipped cleanly where absent)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("FLEETMAP_DATA", ROOT.parent / "shared" / "data"))


def data_path(*parts: str) -> Path:
    """Path under the shared data folder, or skip the test where it is absent."""
    p = DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


@pytest.fixture(scope="session")
def sun3d() -> Path:
    return data_path("sun3d_studyroom")


@pytest.fixture(scope="session")
def corridor() -> Path:
    return data_path("rtabmap_corridor")


@pytest.fixture(scope="session")
def tum_pairs() -> Path:
    return data_path("tum_fr1_xyz")


@pytest.fixture(scope="session")
def vocabulary():
    from shared.vocabulary import load_vocabulary

    return load_vocabulary()


def read_tum_pose(path: Path) -> np.ndarray:
    from shared.geometry import pose_from_tum

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
