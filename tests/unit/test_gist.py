import cv2
import numpy as np
import pytest

from fleetmap.errors import BadInput
from fleetmap.gist import DEFAULT_PARAMS, GistParams, compute_gist
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


def _gist_reference(image, p=DEFAULT_PARAMS):
    """The same descriptor in float64 with SciPy's FFT, step by step."""
    import scipy.fft as sfft

    from fleetmap.gist import _prefilter_gauss, gabor_bank, to_gray_square

    img = np.log1p(to_gray_square(image, p.image_size).astype(np.float64))
    padded = np.pad(img, 5, mode="symmetric")
    gf = _prefilter_gauss(padded.shape[0], p.prefilter_fc)
    out = padded - np.real(sfft.ifft2(sfft.fft2(padded) * gf))
    local = np.sqrt(np.abs(np.real(sfft.ifft2(sfft.fft2(out**2) * gf))))
    out = (out / (0.2 + local))[5:-5, 5:-5]
    b, s, k = p.boundary, p.image_size, p.blocks
    resp = sfft.ifft2(sfft.fft2(np.pad(out, b, mode="symmetric"))[None] * gabor_bank(p))
    crop = np.abs(resp[:, b : b + s, b : b + s])
    g = crop.reshape(len(crop), k, s // k, k, s // k).mean(axis=(2, 4))
    g = g.transpose(0, 2, 1).ravel()
    return g / np.linalg.norm(g)


def test_numpy_fft_gist_matches_a_float64_scipy_reference(corridor, sun3d):
    """GIST runs on the robot with numpy's FFT (no SciPy there): within float32 rounding
    (1.4e-5 at most measured) of the same descriptor in float64 with SciPy."""
    paths = sorted((corridor / "images").glob("*.jpg"))[::6]
    paths += sorted((sun3d / "robot_b" / "rgb").glob("*.png"))[::6]
    for path in paths:
        img = imread(path)
        np.testing.assert_allclose(compute_gist(img), _gist_reference(img), atol=3e-5)
