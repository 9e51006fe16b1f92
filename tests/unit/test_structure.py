"""The house's shape, drawn from the imports: one import name (`fleetmap`), a core without
web code, no import cycle, modules and functions a reader can hold in mind."""

from __future__ import annotations

import ast
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"fleetmap": ROOT / "shared", "fleetmap.services": ROOT / "services"}
WEB = ("fastapi", "starlette", "uvicorn")


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([pkg, *parts])
            if pkg == "fleetmap" and parts[:1] == ["services"]:
                continue
            mods[name] = path
    return mods


def _imports(path: Path, top_level_only: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else ast.walk(tree)
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_nothing_imports_a_generic_shared_or_services():
    files = [*_modules().values(), *ROOT.glob("tests/**/*.py"), *ROOT.glob("bench/*.py")]
    bad = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in files
        for m in _imports(p, top_level_only=False)
        if m.split(".")[0] in ("shared", "services")
    ]
    assert bad == []


def test_the_core_imports_no_web_code_and_no_service():
    for name, path in _modules().items():
        if name.startswith("fleetmap.services"):
            continue
        bad = [
            m
            for m in _imports(path, top_level_only=False)
            if m.split(".")[0] in WEB or m.startswith("fleetmap.services")
        ]
        assert bad == [], name


def test_no_import_cycle():
    mods = _modules()
    graph = {
        name: {m for m in _imports(path, top_level_only=True) if m in mods and m != name}
        for name, path in mods.items()
    }
    state: dict[str, int] = {}

    def visit(n: str, trail: list[str]) -> None:
        state[n] = 1
        for m in graph[n]:
            if state.get(m) == 1:
                pytest.fail(f"import cycle: {' -> '.join(trail[trail.index(m) :] + [n, m])}")
            if m not in state:
                visit(m, trail + [n])
        state[n] = 2

    for n in graph:
        if n not in state:
            visit(n, [])


def test_modules_and_functions_stay_small():
    """No module over 400 lines, no function over 60 (the issue's bar; most are far under)."""
    for name, path in _modules().items():
        text = path.read_text()
        assert text.count("\n") <= 400, f"{name}: {text.count(chr(10))} lines"
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                assert n <= 60, f"{name}.{node.name}: {n} lines"


def test_alignment_types_load_neither_torch_nor_open3d():
    code = (
        "import sys, fleetmap.align.types, fleetmap.place.types, fleetmap.services.cli;"
        "print(sorted(m for m in ('torch', 'open3d') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


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
