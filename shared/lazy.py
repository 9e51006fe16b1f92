"""Heavy modules imported on first use, so that a service or a robot-side import starts in
well under a second (torch takes about a second, Open3D about 0.6 s)."""

from __future__ import annotations

import functools
import importlib


class LazyModule:
    """Stands for `module` (or `module.path.to.attr`) until an attribute is first read."""

    def __init__(self, module: str, attr: str = ""):
        self._module, self._attr = module, attr

    @functools.cached_property
    def _target(self):
        target = importlib.import_module(self._module)
        for part in filter(None, self._attr.split(".")):
            target = getattr(target, part)
        return target

    def __getattr__(self, name: str):
        if name.startswith("__"):  # copy, pickle and introspection probes
            raise AttributeError(name)
        return getattr(self._target, name)
