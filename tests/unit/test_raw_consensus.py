"""A consensus of a few percent of the matches: guided RANSAC finds it where chance gives
little (`registration.ransac_guided`, `align.hypotheses.raw_hypotheses`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fleetmap.align.hypotheses import raw_hypotheses
from fleetmap.align.types import DEFAULT_ALIGN
from fleetmap.correspondences import Correspondences
from fleetmap.geometry import transform_error
from fleetmap.registration import ransac_guided


def _room_matches(rng, n=4000, right=80, noise=0.015):
    """Matches in a 4 x 4 x 2.5 m room: `right` of them agree with T (1.5 cm noise), the
    others pair random points of the two maps. (X in B's map, Y in A's, T mapping X to Y)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [70, 4, -3], degrees=True).as_matrix()
    T[:3, 3] = [1.5, -0.7, 0.2]
    Y = rng.uniform([0, 0, 0], [4, 4, 2.5], (n, 3))
    X = rng.uniform([0, 0, 0], [4, 4, 2.5], (n, 3))
    X[:right] = (Y[:right] - T[:3, 3]) @ T[:3, :3] + rng.normal(0, noise, (right, 3))
    return X, Y, T


def test_guided_ransac_finds_two_percent_right_matches():
    X, Y, T = _room_matches(np.random.default_rng(1))
    T_est, inl = ransac_guided(X, Y, DEFAULT_ALIGN.ransac_tol_m)
    dt, dr = transform_error(T_est, T)
    assert dt < 0.03 and dr < 1.0, (dt, dr)
    assert inl[:80].mean() > 0.9 and inl[80:].sum() < 20


def test_raw_hypotheses_offer_the_consensus_and_nothing_from_chance():
    rng = np.random.default_rng(2)
    X, Y, T = _room_matches(rng)
    C = Correspondences(X, Y, rng.integers(0, 40, len(X)))
    hyps = raw_hypotheses(C, DEFAULT_ALIGN)
    assert hyps and hyps[0].support >= 72 and transform_error(hyps[0].T_a_b, T)[0] < 0.03
    # the same matches with the right ones' A points shuffled away: chance alone
    Y2 = Y.copy()
    Y2[:80] = rng.uniform([0, 0, 0], [4, 4, 2.5], (80, 3))
    assert raw_hypotheses(Correspondences(X, Y2, C.pair), DEFAULT_ALIGN) == []
