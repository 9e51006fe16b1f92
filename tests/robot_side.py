"""A robot-side install (`pip install fleetmap`, without the `server` extra) in a
subprocess: every library of the server extra is made absent before anything is imported.

Building a real slim venv takes minutes (docs/OPERATIONS.md measures one); here the same
interpreter runs with `sys.modules[name] = None` for each server import name, which makes
`import name` raise ModuleNotFoundError and `importlib.util.find_spec(name)` answer None,
as on a machine without the package.
"""

from __future__ import annotations

import os
import subprocess
import sys

from tests.servers import ROOT

#: The `server` extra's distributions (pyproject.toml) and the import names each installs,
#: with those of their own dependencies that a robot must not need either.
SERVER_IMPORTS: dict[str, tuple[str, ...]] = {
    "fastapi": ("fastapi", "starlette"),
    "uvicorn": ("uvicorn",),
    "pydantic": ("pydantic", "pydantic_core"),
    "pydantic-settings": ("pydantic_settings",),
    "python-multipart": ("multipart", "python_multipart"),
    "scipy": ("scipy",),
    "scikit-learn": ("sklearn",),
    "torch": ("torch",),
    "open3d": ("open3d",),
    "faiss-cpu": ("faiss",),
    "matplotlib": ("matplotlib",),
    "pillow": ("PIL",),
    "swagger-ui-bundle": ("swagger_ui_bundle",),
    "psycopg": ("psycopg", "psycopg_binary"),
    "psycopg-pool": ("psycopg_pool",),
    "mcap": ("mcap",),
    "mcap-protobuf-support": ("mcap_protobuf",),
    "foxglove-schemas-protobuf": ("foxglove_schemas_protobuf",),
    "gtsam": ("gtsam",),
}
BLOCKED = tuple(name for names in SERVER_IMPORTS.values() for name in names)

_PRELUDE = f"import sys\nfor _name in {BLOCKED!r}:\n    sys.modules[_name] = None\n"


def run_python(code: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """`code` run by a robot-side interpreter (cwd: the project root)."""
    return subprocess.run(
        [sys.executable, "-c", _PRELUDE + code, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "FLEETMAP_TOKEN": ""},
        timeout=timeout,
    )


def run_cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """`fleetmap ARGS...` on a robot-side install."""
    return run_python(
        "from fleetmap.services.cli import main\nsys.exit(main(sys.argv[1:]))",
        *args,
        timeout=timeout,
    )
