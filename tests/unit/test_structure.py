"""The house's shape, drawn from the imports: one import name (`fleetmap`), a core without
web code, no import cycle, modules and functions a reader can hold in mind."""

from __future__ import annotations

import ast
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


def test_the_schedulers_names_are_real_tests():
    """Every test the suite's scheduler names (`tests/scheduling.py`: its costs, the tests
    run apart and the shared groups) is a module or a test function that exists: a renamed
    test would silently lose its place in the longest-first order."""
    from tests.scheduling import APART, COST_S, SHARED

    groups = set(SHARED.values())
    names = [*APART, *SHARED, *(k for k in COST_S if k not in groups)]
    for name in names:
        module, _, test = name.partition("::")
        path = ROOT / module
        assert path.is_file(), name
        if test:
            func = test.split("[", 1)[0]
            defined = {
                n.name
                for n in ast.walk(ast.parse(path.read_text()))
                if isinstance(n, ast.FunctionDef)
            }
            assert func in defined, name
