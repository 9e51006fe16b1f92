"""The 3D view's binary cloud (issue 25): layout, cap."""

import numpy as np
import pytest

from fleetmap.fleet.map_scene import MAX_POINTS, cloud_bytes, thinned


def test_cloud_bytes_are_float32_xyz_then_rgb():
    rng = np.random.default_rng(0)
    pts, cols = rng.normal(size=(1000, 3)), rng.integers(0, 256, (1000, 3), dtype=np.uint8)
    body = cloud_bytes(pts, cols)
    assert len(body) == 15 * 1000
    xyz = np.frombuffer(body, "<f4", 3000).reshape(-1, 3)
    np.testing.assert_array_equal(xyz, pts.astype(np.float32))
    np.testing.assert_array_equal(np.frombuffer(body, np.uint8, offset=12000).reshape(-1, 3), cols)
    with pytest.raises(ValueError, match=r"shape \(N, 3\), got \(1000, 2\)"):
        cloud_bytes(pts[:, :2], cols[:, :2])


def test_a_large_cloud_is_thinned_evenly_to_the_cap():
    pts = np.arange(3 * 250_000, dtype=float).reshape(-1, 3)
    cols = np.zeros((250_000, 3), np.uint8)
    p, c = thinned(pts, cols)
    assert len(p) == len(c) == MAX_POINTS and len(cloud_bytes(p, c)) <= 2_000_000
    assert (p[0] == pts[0]).all() and (p[-1] == pts[-1]).all()  # spread over the whole cloud
    small = pts[:10]
    assert thinned(small, cols[:10])[0] is small
