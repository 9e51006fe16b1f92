"""`fleetmap.matching.mutual_best` answers as `S.argmax(0)[best] == rows`, ties included
(integer descriptors give integer distances: rows tie on a column's maximum)."""

from __future__ import annotations

import numpy as np

from fleetmap.matching import mutual_best


def test_mutual_best_is_argmax_down_the_columns_with_ties():
    rng = np.random.default_rng(3)
    for _ in range(200):
        n, m = rng.integers(2, 40, size=2)
        S = rng.integers(0, 6, size=(n, m)).astype(np.float32)  # many ties
        rows = np.arange(n)
        best = S.argmax(1)
        assert (mutual_best(S, rows, best) == (S.argmax(0)[best] == rows)).all()
