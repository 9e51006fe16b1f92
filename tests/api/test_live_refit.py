"""The live map keeps a merged pair's fit when a refit sits worse on the robots' surfaces
(issue 23: last fits never end worse than the fit they replace)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fleetmap.dataset import read_recording
from fleetmap.fleet.merge_rules import new_merge, refit_or_kept
from fleetmap.fleet.view_choice import load_view

PAIR = Path(__file__).resolve().parents[2] / "examples" / "fr1_pair"


def _views():
    a, b = (read_recording(PAIR / r) for r in ("alpha", "bravo"))
    return [[load_view(a, 0)], [load_view(b, 0)]]


def _state(T: np.ndarray, **more) -> dict:
    base = {"status": "merged", "transform": T.tolist(), "evidence": 1, "attempts": 1}
    return base | {"budget": 8, "since": [1, 1], "views": [1, 1], "at": 1.0} | more


def test_a_refit_that_sits_worse_keeps_the_earlier_fit():
    T_true = np.loadtxt(PAIR / "T_alpha_bravo.txt")
    off = T_true.copy()
    off[:3, 3] += [0.06, 0.0, 0.0]
    views = _views()
    before = _state(T_true)
    worse = _state(off, evidence=3, attempts=2, budget=12, at=2.0)
    kept = refit_or_kept(before, worse, lambda: views)
    assert kept["transform"] == before["transform"]
    assert (kept["attempts"], kept["budget"], kept["evidence"]) == (2, 12, 3)
    assert "whole maps" in kept["kept"] and not new_merge(kept)
    better = refit_or_kept(_state(off), _state(T_true, attempts=2, at=2.0), lambda: views)
    assert better["transform"] == T_true.tolist() and "kept" not in better
    assert better["surface_rmse_m"] < 0.03 and new_merge(better)


def test_a_first_fit_is_taken_as_it_comes():
    T = np.eye(4)

    def unused():
        raise AssertionError("a first fit is not judged")

    assert refit_or_kept(None, _state(T), unused) == _state(T)
    refused = {"status": "refused", "evidence": 1}
    assert refit_or_kept(refused, _state(T), unused) == _state(T)
