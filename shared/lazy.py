"""Heavy modules imported on first use, so that a service or a robot-side import starts in
well under a second (torch takes about a second, Open3D about 0.6 s), and a robot-side
install (`pip install fleetmap`, without the `server` extra) says what it lacks in one line.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util

from fleetmap.errors import MissingDependency

#: The fix for a missing library of the `server` extra.
SERVER_FIX = "pip install 'fleetmap[server]'"
#: Import names of the `server` extra that the services and `fleetmap merge` need.
SERVER_MODULES = (
    "fastapi",
    "uvicorn",
    "scipy",
    "faiss",
    "torch",
    "open3d",
    "matplotlib",
    "mcap_protobuf",  # fleet.mcap: merge and map write it
    "foxglove_schemas_protobuf",
)


def require(what: str, modules: tuple[str, ...] = SERVER_MODULES) -> None:
    """MissingDependency naming the fix unless every module in `modules` is installed;
    checked without importing any (before the work that needs them, not midway)."""
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise MissingDependency(
            f"{what} needs the server dependencies ({', '.join(missing)} not installed): "
            f"{SERVER_FIX}"
        )


class LazyModule:
    """Stands for `module` (or `module.path.to.attr`) until an attribute is first read."""

    def __init__(self, module: str, attr: str = ""):
        self._module, self._attr = module, attr

    @functools.cached_property
    def _target(self):
        try:
            target = importlib.import_module(self._module)
        except ModuleNotFoundError as exc:
            if exc.name != self._module.split(".")[0]:
                raise  # a broken install of the module itself: the real traceback
            raise MissingDependency(f"{exc.name} is not installed: {SERVER_FIX}") from exc
        for part in filter(None, self._attr.split(".")):
            target = getattr(target, part)
        return target

    def __getattr__(self, name: str):
        if name.startswith("__"):  # copy, pickle and introspection probes
            raise AttributeError(name)
        return getattr(self._target, name)
