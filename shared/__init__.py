"""fleetmap's algorithm core: frame structures, retrieval and alignment, with no web code."""

import sys as _sys
import types as _types

__version__ = "0.1.0"


def _without_open3d_plotly() -> None:
    """Open3D imports its Plotly viewer on every import (`open3d.visualization.draw_plotly`:
    Dash, Plotly, Flask, IPython: 0.62 -> 0.33 s on a quiet machine, 0.77 of 1.14 s in a merge),
    in every process that uses it: the merge, each service, each pytest worker. fleetmap
    never draws with it, so where fleetmap is imported before Open3D that module is a stand-in
    whose functions say how to get the real one."""
    name = "open3d.visualization.draw_plotly"
    if "open3d" in _sys.modules or name in _sys.modules:
        return

    def unavailable(*args, **kwargs):
        raise RuntimeError(
            "Open3D's Plotly viewer is not loaded where fleetmap was imported first "
            "(it costs most of Open3D's import time); import open3d before fleetmap to use it"
        )

    stub = _types.ModuleType(name, "A stand-in for Open3D's Plotly viewer (fleetmap/__init__)")
    stub.get_plotly_fig = stub.draw_plotly = stub.draw_plotly_server = unavailable
    _sys.modules[name] = stub


_without_open3d_plotly()
