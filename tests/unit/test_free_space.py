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


def test_a_floor_widens_the_tolerance_at_the_depth_read():
    """A point 10 cm in front of the wall (3 m): a firm conflict at 5 cm + 2%; supported
    where the depth's noise floor there is 12 cm; the floor is read at the wall's depth."""
    view = edge_view()
    point = at_pixel(500, 240, 2.9)
    assert free_space_check(point, [view], 0.05, 0.0) == (0, 1, 1)
    assert free_space_check(point, [view], 0.05, 0.0, lambda d: 0.04 * d) == (1, 0, 0)
    assert free_space_check(point, [view], 0.05, 0.0, lambda d: 0.04 * (d < 2)) == (0, 1, 1)


def test_depth_noise_measures_an_active_stereo_cameras_error(hololens):
    """HoloLens walk views (a time-of-flight camera, its own noise under 2 cm to 3.5 m)
    through a D435's simulated error (3.7 mm x depth squared, `simulate`): what the measure
    adds in each band of depth with enough readings is the model's spread of the difference
    of two readings (sqrt(2) x 3.7 mm x depth squared) within 30%, and it never falls with
    depth."""
    from dataclasses import replace

    from fleetmap.dataset import read_recording
    from fleetmap.depth_noise import EDGES, DepthNoise, _differences
    from fleetmap.fleet.view_choice import load_view
    from fleetmap.simulate import D435_SIGMA_1M, stereo_depth_noise

    rec = read_recording(hololens / "hl_a")
    views = [load_view(rec, i) for i in range(60, 120, 5)]
    rng, scale, sigma = np.random.default_rng(0), views[0].intrinsics.depth_scale, D435_SIGMA_1M
    noisy = [
        replace(
            v,
            depth=np.round(scale * stereo_depth_noise(v.depth / scale, sigma, rng)).astype(
                np.uint16
            ),
        )
        for v in views
    ]
    clean, through = DepthNoise.measure(views).sigma, DepthNoise.measure(noisy).sigma
    assert np.all(np.diff(through) >= 0) and np.all(through >= clean - 0.002)
    read = _differences(noisy, 8, 6.0)[0]
    centres = (EDGES[:-1] + EDGES[1:]) / 2
    counted = np.histogram(read, EDGES)[0] >= 2000
    assert counted.sum() >= 4, counted
    added = np.sqrt(through**2 - clean**2)[counted]
    model = np.sqrt(2) * D435_SIGMA_1M * centres[counted] ** 2
    assert np.all(np.abs(added / model - 1) < 0.3), (added, model)
