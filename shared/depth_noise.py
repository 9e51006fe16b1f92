"""How far a robot's own depth readings disagree, by depth: the noise a free-space test of
its map is judged at.

A depth camera errs more the farther it sees (active stereo and structured light as the
depth squared: an Intel D435 about 1.5 cm at 2 m, 6 cm at 4 m; a Kinect v1 a third of
that), and a robot's own SLAM adds its pose error on top. Both show where two of the
robot's views see the same surface: the depth one view's pixels reach in the other
differs from what the other measured there. `DepthNoise.measure` takes that difference
over every ordered pair of a robot's views, off depth edges, and keeps its robust spread
(1.4826 x the median absolute difference) per band of depth: the sensor's and the
trajectory's noise together, as the robot's own data show them, with no model of the
camera assumed.

A test that judges another robot's map against this robot's depth tighter than the robot
agrees with itself refuses the truth: HoloLens windows through a D435's noise with the
other robot a 16:9 camera, the true alignment firm 0.78-0.88 at 2.5% of the depth where
the same windows without the noise are 0.93-0.99 (docs/ALIGNER.md, session 38).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmap.mapcloud import MAX_DEPTH_M, SeenDepth, off_edge_points

#: depth bands (metres): half a metre wide where cameras see most, wider beyond
EDGES = np.array([0.0, 0.75, 1.25, 1.75, 2.25, 2.75, 3.25, 3.75, 4.5, 5.5, 7.0])
#: differences this far apart or more belong to another surface (an occlusion, a window of
#: the map the other view never saw), not to noise: 10% of the depth and 5 cm
WINDOW_REL, WINDOW_M = 0.1, 0.05
#: fewer differences than this in a band: its spread is taken from the nearest band
MIN_SAMPLES = 200


@dataclass(frozen=True)
class DepthNoise:
    """The robust spread (metres) of the difference between two depth readings of one
    surface, per band of depth (`EDGES`), never falling with depth."""

    sigma: np.ndarray  # ndarray of shape (len(EDGES) - 1,)

    @classmethod
    def measure(
        cls, views: Sequence, stride: int = 8, max_depth: float = MAX_DEPTH_M
    ) -> DepthNoise:
        """From one robot's RGB-D views (every `stride`-th pixel, off depth edges: a pixel
        whose neighbourhood spans over 5% of its depth may mix both sides of the edge)."""
        d, r = _differences(views, stride, max_depth)
        band = np.digitize(d, EDGES) - 1
        sigma = np.full(len(EDGES) - 1, np.nan)
        for k in range(len(sigma)):
            rk = r[band == k]
            if len(rk) >= MIN_SAMPLES:
                sigma[k] = 1.4826 * float(np.median(np.abs(rk)))
        known = np.flatnonzero(np.isfinite(sigma))
        if not len(known):
            return cls(np.zeros(len(sigma)))
        for k in np.flatnonzero(~np.isfinite(sigma)):
            sigma[k] = sigma[known[np.argmin(np.abs(known - k))]]
        return cls(np.maximum.accumulate(sigma))

    def between(self, other: DepthNoise) -> DepthNoise:
        """The spread between one reading of this robot's and one of the other's: the
        root mean square of the two (each is already that of two readings)."""
        return DepthNoise(np.sqrt((self.sigma**2 + other.sigma**2) / 2))

    def __call__(self, depth: np.ndarray) -> np.ndarray:
        """The spread at each depth (metres), interpolated between the bands' centres."""
        return np.interp(depth, (EDGES[:-1] + EDGES[1:]) / 2, self.sigma)


def _differences(views: Sequence, stride: int, max_depth: float):
    """(depth read, point's depth - depth read) of every view's pixels seen in every other
    view, within `WINDOW_REL` x depth + `WINDOW_M`."""
    points = [off_edge_points(v, stride, max_depth) for v in views]
    read, diff = [np.zeros(0)], [np.zeros(0)]
    for j, v in enumerate(views):
        seen = SeenDepth(v)
        for i, pts in enumerate(points):
            if i == j or not len(pts):
                continue
            z, d, _, _ = seen.read(pts)
            r = z - d
            near = (d > 0) & (np.abs(r) < WINDOW_REL * d + WINDOW_M)
            read.append(d[near])
            diff.append(r[near])
    return np.concatenate(read), np.concatenate(diff)
