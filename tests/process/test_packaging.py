"""The package as a fresh interpreter and pip see it: what an import loads, which
`fleetmap` a user's folder gets, what the wheel holds (subprocesses)."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_alignment_types_load_neither_torch_nor_open3d():
    code = (
        "import sys, fleetmap.align.types, fleetmap.place.types, fleetmap.services.cli;"
        "print(sorted(m for m in ('torch', 'open3d') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_open3d_under_fleetmap_skips_its_plotly_viewer_and_says_so():
    """Open3D's Plotly viewer (Dash, Flask, IPython) is most of its import; fleetmap's
    registration works without it, and asking for the viewer names the way to get it."""
    code = (
        "import sys, fleetmap, open3d\n"
        "from fleetmap.mapcloud import REG\n"
        "REG.TransformationEstimationPointToPlane()\n"
        "print(sorted(m for m in ('dash', 'plotly', 'IPython') if m in sys.modules))\n"
        "try:\n"
        "    open3d.visualization.draw_plotly([])\n"
        "except RuntimeError as e:\n"
        "    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded, message = out.stdout.splitlines()
    assert loaded == "[]"
    assert "import open3d before fleetmap" in message


def test_import_fleetmap_from_a_user_folder_with_its_own_shared(tmp_path):
    """A user project with its own `shared/` and `services/` (here: both raise on import)
    still gets ours as `fleetmap`, and the console script's module."""
    for name in ("shared", "services"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise ImportError('user {name}')\n")
    code = (
        "import fleetmap.place, fleetmap.align, fleetmap.services.cli, shared;"
        "print(fleetmap.__name__)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert "user shared" in out.stderr  # the user's own package, not ours
    code = "import fleetmap.place, fleetmap.align, fleetmap.services.cli as c; print(c.main)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_the_wheel_installs_only_fleetmap(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation"]
        + ["-w", str(tmp_path), str(ROOT)],
        check=True,
        capture_output=True,
    )
    (wheel,) = tmp_path.glob("fleetmap-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"fleetmap"}
    for module in ("place/db.py", "align/pipeline.py", "services/cli.py", "wire.py"):
        assert f"fleetmap/{module}" in names
    assert "fleetmap/assets/default_vocabulary.npz" in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "fleetmap = fleetmap.services.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()
