import cv2
import numpy as np
import pytest

from fleetmap.errors import BadInput
from fleetmap.gist import GistParams, compute_gist
from tests.conftest import imread


def test_shape_norm_and_determinism(corridor):
    img = imread(corridor / "images" / "1.jpg")
    g = compute_gist(img)
    assert g.shape == (384,) and g.dtype == np.float32
    assert np.linalg.norm(g) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_array_equal(g, compute_gist(img))


def test_configurable_size_and_bank():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    g = compute_gist(img, GistParams(image_size=64, orientations=(4, 4), blocks=2))
    assert g.shape == (2 * 4 * 4,)


def test_shifted_and_brightened_image_stays_closer_than_another_scene(sun3d, corridor):
    img = imread(sorted((sun3d / "robot_a" / "rgb").glob("*.png"))[0])
    shifted = np.roll(img, (12, 16), axis=(0, 1))
    brighter = cv2.convertScaleAbs(img, alpha=1.3, beta=25)
    other_room = imread(corridor / "images" / "30.jpg")
    other_view = imread(sorted((sun3d / "robot_b" / "rgb").glob("*.png"))[0])
    g = compute_gist(img)
    d_shift = np.linalg.norm(g - compute_gist(shifted))
    d_bright = np.linalg.norm(g - compute_gist(brighter))
    d_other = min(np.linalg.norm(g - compute_gist(x)) for x in (other_room, other_view))
    assert d_shift < 0.5 * d_other
    assert d_bright < 0.5 * d_other


def test_rejects_bad_images():
    with pytest.raises(BadInput, match=r"shape \(H, W\) or \(H, W, 3\)"):
        compute_gist(np.zeros((10, 10, 4), np.uint8) + 1)
    with pytest.raises(BadInput, match="too small"):
        compute_gist(np.zeros((8, 8), np.uint8))
    with pytest.raises(BadInput, match="multiple of blocks"):
        GistParams(image_size=30)
