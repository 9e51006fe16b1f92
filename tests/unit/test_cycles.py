"""Fits around a cycle must agree (issue 26.2): the placement goes through the strongest
fits, and a weaker fit that closes a cycle and disagrees stops every robot placed through
the cycle, whatever the inliers say."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fleetmap.fleet.cycles import CycleParams, disagreeing
from fleetmap.fleet.placement import spanning_placement
from tests.conftest import random_frame


def fleet(noise_m: float = 0.0):
    """Four robots' true frames in A's, and the fits of every pair (noisy by noise_m)."""
    truth = {"A": np.eye(4), "B": random_frame(1), "C": random_frame(2), "D": random_frame(3)}
    rng = np.random.default_rng(7)
    edges = {}
    for a, b, inliers in (("A", "B", 52), ("B", "C", 300), ("A", "C", 200), ("C", "D", 90)):
        T = np.linalg.inv(truth[a]) @ truth[b]
        T[:3, 3] += rng.normal(0, noise_m, 3)
        edges[(a, b)] = {"T_a_b": T, "inliers": inliers}
    return truth, edges


def test_honest_cycles_within_the_sensor_noise_pass():
    _, edges = fleet(noise_m=0.02)
    placed, chain = spanning_placement(["A", "B", "C", "D"], edges)
    assert disagreeing(placed, chain, edges) == {}


def test_a_strong_wrong_fit_stops_the_robots_of_its_cycle():
    """A wrong A-C fit with 16,074 inliers (as a copier's had) against B's own fit with A
    of 52: neither B nor C is placed on it, nor D (placed through C)."""
    truth, edges = fleet()
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    wrong[0, 3] = 5.0
    edges[("A", "C")]["T_a_b"] = edges[("A", "C")]["T_a_b"] @ wrong  # C now 5 m off
    edges[("A", "C")]["inliers"] = 16074
    placed, chain = spanning_placement(["A", "B", "C", "D"], edges)
    bad = disagreeing(placed, chain, edges)
    assert set(bad) == {"B", "C", "D"}, bad
    assert "disagree around the cycle A-B-C-A" in bad["B"] and "90.0 deg" in bad["C"]
    assert "placed through C" in bad["D"]
    tight = CycleParams(max_translation_m=1e-9, max_rotation_deg=1e-9)
    exact = fleet()[1]  # noise-free fits agree even at a tolerance of nothing
    assert disagreeing(*spanning_placement(["A", "B", "C", "D"], exact), exact, tight) == {}
