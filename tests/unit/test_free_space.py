"""The free-space test: a point the camera saw through is a conflict, and a firm one unless
a surface lies within the tolerance sideways (a point a few pixels beside a depth edge)."""

import numpy as np

from fleetmap.camera import TUM_FR1
from fleetmap.correspondences import RGBDView
from fleetmap.mapcloud import SeenDepth, free_space_check


def edge_view() -> RGBDView:
    """A wall 3 m away, a box face 1 m away on the image's left half (columns < 320)."""
    depth = np.full((480, 640), 3.0)
    depth[:, :320] = 1.0
    depth = np.round(depth * TUM_FR1.depth_scale).astype(np.uint16)
    return RGBDView(np.zeros((480, 640, 3), np.uint8), depth, TUM_FR1, np.eye(4))


def at_pixel(u: float, v: float, z: float) -> np.ndarray:
    """The camera-frame point (= map frame here) seen at pixel (u, v), depth z."""
    return np.array([[(u - TUM_FR1.cx) * z / TUM_FR1.fx, (v - TUM_FR1.cy) * z / TUM_FR1.fy, z]])


def test_a_point_on_a_surface_is_supported_and_one_in_seen_space_conflicts():
    view = edge_view()
    assert free_space_check(at_pixel(500, 240, 3.0), [view]) == (1, 0, 0)
    # 1.5 m in front of the wall, far from the box: the camera saw the wall through it
    assert free_space_check(at_pixel(500, 240, 1.5), [view]) == (0, 1, 1)
    # behind the box: occluded, tells nothing
    assert free_space_check(at_pixel(100, 240, 2.0), [view]) == (0, 0, 0)


def test_a_point_beside_a_depth_edge_is_no_firm_conflict():
    """The box's edge point, 3 pixels into the wall's side (0.6 cm at 1 m, within the
    tolerance there: 5 cm + 2% of the wall's 3 m): the wall at its pixel is 2 m farther,
    but the box is within the tolerance sideways: a conflict along the ray, not a firm
    one."""
    view = edge_view()
    point = at_pixel(323, 240, 1.0)
    assert free_space_check(point, [view]) == (0, 1, 0)
    assert free_space_check(point, [SeenDepth(view)]) == (0, 1, 0)  # kept form, same answer
    # 60 pixels into the wall's side (12 cm at 1 m): beyond it, a firm conflict
    assert free_space_check(at_pixel(380, 240, 1.0), [view]) == (0, 1, 1)
