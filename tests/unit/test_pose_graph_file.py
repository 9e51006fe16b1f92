"""The robots' pose graph file (`pose_graph.g2o` where no keyframe graph is applied), read
back by GTSAM's g2o reader."""

from __future__ import annotations

import numpy as np

from fleetmap.services.outputs import write_g2o


def test_robots_not_placed_are_said_not_listed_as_vertices(tmp_path):
    """The header listed every robot as "vertex k = robot ..." while only placed robots have
    a vertex (an outside tester's review of the live map's file)."""
    import gtsam

    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.5]
    placed = {"alpha": np.eye(4), "bravo": T}
    edges = {("alpha", "bravo"): {"T_a_b": T, "inliers": 40}}
    path = tmp_path / "pose_graph.g2o"
    write_g2o(path, ["alpha", "bravo", "charlie"], placed, edges)
    lines = path.read_text().splitlines()
    assert lines[0] == "# fleetmap pose graph: vertex robot: 0 alpha, 1 bravo"
    assert lines[1] == "# not placed (no vertex): charlie"
    graph, values = gtsam.readG2o(str(path), True)
    assert values.size() == 2 and graph.size() == 1
    np.testing.assert_allclose(values.atPose3(1).translation(), [1.0, 2.0, 0.5], atol=1e-9)
