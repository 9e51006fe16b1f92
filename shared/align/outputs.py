"""What the aligner returns beside the fit: the merged cloud of a request's views."""

from __future__ import annotations

import numpy as np

from fleetmap.align.types import AlignResult, unique_views
from fleetmap.mapcloud import ROBOT_COLOURS, views_cloud


def merged_cloud(
    pairs, result: AlignResult, colour: str = "robot", voxel: float = 0.03
) -> tuple[np.ndarray, np.ndarray]:
    """A's views and B's views mapped into A's frame: points (N, 3) and colours (N, 3)."""
    ca = views_cloud(unique_views(pairs, 0), voxel=voxel)
    cb = views_cloud(unique_views(pairs, 1), voxel=voxel)
    pa, pb = np.asarray(ca.points), result.map_points(np.asarray(cb.points))
    if colour == "image" and ca.has_colors() and cb.has_colors():
        cols = np.concatenate([np.asarray(ca.colors), np.asarray(cb.colors)])
    else:
        cols = np.concatenate(
            [np.tile(ROBOT_COLOURS[0], (len(pa), 1)), np.tile(ROBOT_COLOURS[1], (len(pb), 1))]
        )
    return np.concatenate([pa, pb]), cols
