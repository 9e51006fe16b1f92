"""The rigid placement of a fleet from pairwise fits: the strongest links chained."""

import numpy as np

from fleetmap.fleet.placement import spanning_placement


def test_spanning_placement_chains_strongest_links_and_leaves_isolated_robots():
    def shift(x):
        T = np.eye(4)
        T[0, 3] = x
        return T

    edges = {
        ("A", "B"): {"T_a_b": shift(1), "inliers": 50},
        ("B", "C"): {"T_a_b": shift(2), "inliers": 80},
        ("A", "C"): {"T_a_b": shift(10), "inliers": 5},
    }
    placed, chain = spanning_placement(["A", "B", "C", "D"], edges)
    assert set(placed) == {"A", "B", "C"}
    assert chain["C"] == ["A", "B", "C"] and placed["C"][0, 3] == 3.0
