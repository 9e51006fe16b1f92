"""When the fleet graph is worth building (issue 22): a robot's path must be long enough for
the drift model to bend its map by the correction's gate."""

from types import SimpleNamespace

import numpy as np

from fleetmap.fleet.correct import CorrectionParams, correct_fleet, drift_bound


def _robot(length_m: float, n: int = 12) -> list:
    """n keyframes along a straight path of `length_m` (only stamps and poses)."""
    out = []
    for k, x in enumerate(np.linspace(0.0, length_m, n)):
        T = np.eye(4)
        T[0, 3] = x
        out.append(SimpleNamespace(frame=SimpleNamespace(stamp=float(k), T_map_cam=T)))
    return out


def test_short_paths_keep_the_rigid_placement_without_a_graph():
    """A desk seen from one place (0.5 m of path each): the drift model cannot bend such a
    map by 4 cm, so no closure is searched (these keyframes have no features: a search
    would fail) and every robot stays where the rigid placement put it."""
    p = CorrectionParams()
    kfs = {"A": _robot(0.5), "B": _robot(0.5)}
    assert drift_bound(np.stack([k.frame.T_map_cam for k in kfs["A"]]), p.graph) < p.min_bend_m
    T_b = np.eye(4)
    T_b[:3, 3] = [1.0, 2.0, 0.5]
    fleet = correct_fleet(kfs, {"A": np.eye(4), "B": T_b}, {}, [], "A", p)
    assert fleet.skipped and fleet.summary()["closures"] == {"features": 0, "depth": 0, "fit": 0}
    for r, T in (("A", np.eye(4)), ("B", T_b)):
        c = fleet.robots[r]
        assert not c.applied and np.allclose(c.rigid, T)
        assert np.allclose(c.T_ref_kf, T @ np.stack([k.frame.T_map_cam for k in kfs[r]]))
    # three metres of path can bend by more than the gate: the graph is built
    assert drift_bound(np.stack([k.frame.T_map_cam for k in _robot(3.0)]), p.graph) > p.min_bend_m
