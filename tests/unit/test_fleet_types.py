"""The fleet's typed state reads and writes the JSON stored and served before it was typed:
a placement row and a report's fit come back key for key, value for value."""

from __future__ import annotations

import json

import numpy as np

from fleetmap.fleet.state import forget_robot
from fleetmap.fleet.types import Fit, Placement, edge, transform_from_json
from tests.conftest import random_frame

T_AB = random_frame(1)

#: A "map" row as the worker stored it before `Placement` (key order included).
STORED_MAP = {
    "reference": "A",
    "transforms": {"A": np.eye(4).tolist(), "B": T_AB.tolist()},
    "flagged": {"C": "placed through B, whose fits disagree"},
    "version": 7,
    "updated_at": 1700000000.25,
    "optimised": False,
    "edges": [["A", "B", 143]],
}

#: The aligner's answer (`POST /align`), as `fleetmap merge` received it.
ANSWER = {
    "merged": True,
    "reason": "",
    "method": "default",
    "correspondences": 900,
    "inliers": 143,
    "holdout_residual_m": 0.012,
    "icp_fitness": 0.8,
    "mlp_holdout_residual_m": None,
    "hypotheses": [{"inliers": 143}],
    "seconds": 3.5,
    "scene_depth_m": 2.1,
    "transform": T_AB.tolist(),
}


def test_a_stored_placement_row_round_trips():
    text = json.dumps(STORED_MAP)
    p = Placement.from_json(json.loads(text))
    assert p.reference == "A" and p.version == 7 and p.links == [["A", "B", 143]]
    np.testing.assert_array_equal(p.T_ref["B"], T_AB)
    assert json.dumps(p.to_json()) == text  # byte for byte, key order included
    assert Placement.from_json({}).version == 0  # before the first placement
    assert p.same_as(Placement.from_json(json.loads(text)))


def test_forgetting_a_robot_keeps_the_row_layout():
    pairs = {"A|B": {"robot_a": "A", "robot_b": "B", "status": "merged"}}
    new_pairs, new_map = forget_robot(json.dumps(pairs), json.dumps(STORED_MAP), "C")
    m = json.loads(new_map)
    assert new_pairs is None and list(m) == list(STORED_MAP)
    assert m["flagged"] == {} and m["version"] == 8 and m["transforms"] == STORED_MAP["transforms"]


def test_a_fit_writes_the_report_item_as_before():
    fit = Fit.from_json(ANSWER, "A", "B")
    assert fit.merged and fit.inliers == 143 and fit.method == "default"
    np.testing.assert_array_equal(fit.T_a_b, T_AB)
    fit.views, fit.link_overlaps = [12, 12], 40
    before = {"robot_a": "A", "robot_b": "B", "views": [12, 12]}
    before |= {k: v for k, v in ANSWER.items() if k != "hypotheses"} | {"link_overlaps": 40}
    assert json.dumps(fit.to_json()) == json.dumps(before)
    assert Fit.from_json(fit.to_json()).to_json() == fit.to_json()
    e = fit.edge()
    assert e == edge(fit.T_a_b, 143) and set(e) == {"T_a_b", "inliers"}
    refused = Fit.from_json({"merged": False, "reason": "no", "method": "default"}, "A", "B")
    assert refused.T_a_b is None and "transform" not in refused.to_json()
    np.testing.assert_array_equal(transform_from_json(T_AB.tolist()), T_AB)
