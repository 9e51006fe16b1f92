"""`ViewsCloud`: a cloud made without normals (an ICP source) and asked for with normals
later is the cloud made with them; neither kind of request changes what the other sees."""

import numpy as np

from fleetmap.camera import TUM_FR1
from fleetmap.correspondences import RGBDView
from fleetmap.mapcloud import ViewsCloud
from tests.conftest import textured_image


def _views() -> list[RGBDView]:
    """Two views of a tilted floor with a box on it, 1-2 m away."""
    h, w = 480, 640
    v, u = np.mgrid[0:h, 0:w]
    depth = 1.2 + 0.6 * v / h + 0.1 * np.sin(u / 25.0)
    depth[160:320, 200:400] -= 0.3  # the box's face
    depth_raw = np.round(TUM_FR1.depth_scale * depth).astype(np.uint16)
    views = []
    for k in range(2):
        T = np.eye(4)
        T[:3, 3] = [0.05 * k, 0.0, 0.0]
        views.append(RGBDView(textured_image(k, h, w), depth_raw, TUM_FR1, T))
    return views


def test_normals_asked_for_later_are_the_ones_made_at_once():
    at_once, later = ViewsCloud(_views()), ViewsCloud(_views())
    for voxel in (0.02, 0.04):
        bare = later.at(voxel, normals=False)
        assert not bare.has_normals() and len(bare.points) > 500
        full = at_once.at(voxel)
        assert later.at(voxel) is bare and bare.has_normals()  # the same cloud, completed
        np.testing.assert_array_equal(np.asarray(bare.points), np.asarray(full.points))
        np.testing.assert_array_equal(np.asarray(bare.normals), np.asarray(full.normals))
        assert at_once.at(voxel, normals=False).has_normals()  # made with them: kept
