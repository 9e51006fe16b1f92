"""GIST global descriptor (Oliva & Torralba 2001), as in the LEAR reference code.

Grey image -> square resize -> whitening and local contrast normalisation (prefilter)
-> Gabor bank in the frequency domain (3 scales x 8 orientations by default) -> magnitude
of each response averaged over a 4x4 grid of windows: 3 * 8 * 16 = 384 values.

One forward FFT per image and one batched inverse FFT for the whole bank: no Python loop
over pixels or filters. The filter bank is cached per configuration. numpy's FFT, not
SciPy's: GIST is computed on the robot, whose install has no SciPy (descriptors differ from
SciPy's by at most 1.4e-5, float32 rounding, on 134 real frames).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from fleetmap.errors import BadInput


@dataclass(frozen=True)
class GistParams:
    """GIST configuration. The descriptor has `len(orientations) * sum... * blocks**2` values."""

    image_size: int = 32
    orientations: tuple[int, ...] = (8, 8, 8)
    blocks: int = 4
    prefilter_fc: float = 4.0
    boundary: int = 8

    @property
    def dim(self) -> int:
        return sum(self.orientations) * self.blocks**2

    def __post_init__(self) -> None:
        if self.image_size < 8 * self.blocks or self.image_size % self.blocks:
            raise BadInput(
                f"image_size must be a multiple of blocks={self.blocks} and >= "
                f"{8 * self.blocks}, got {self.image_size}"
            )


DEFAULT_PARAMS = GistParams()


@lru_cache(maxsize=8)
def gabor_bank(params: GistParams) -> np.ndarray:
    """Frequency-domain Gabor bank of shape (F, n, n), n = image_size + 2 * boundary."""
    n = params.image_size + 2 * params.boundary
    rows = []
    for i, n_or in enumerate(params.orientations):
        for j in range(n_or):
            rows.append((0.35, 0.3 / 1.85**i, 16.0 * n_or**2 / 32.0**2, np.pi / n_or * j))
    fx, fy = np.meshgrid(np.arange(-n // 2, n // 2), np.arange(-n // 2, n // 2))
    fr = np.fft.fftshift(np.sqrt(fx**2.0 + fy**2.0))
    t = np.fft.fftshift(np.angle(fx + 1j * fy))
    bank = np.empty((len(rows), n, n), dtype=np.float32)
    for k, (a, f0, b, theta) in enumerate(rows):
        tr = t + theta
        tr = tr + 2 * np.pi * (tr < -np.pi) - 2 * np.pi * (tr > np.pi)
        bank[k] = np.exp(-10 * a * (fr / n / f0 - 1) ** 2 - 2 * b * np.pi * tr**2)
    return bank


@lru_cache(maxsize=8)
def _prefilter_gauss(n: int, fc: float) -> np.ndarray:
    s1 = fc / np.sqrt(np.log(2))
    fx, fy = np.meshgrid(np.arange(-n // 2, n // 2), np.arange(-n // 2, n // 2))
    return np.fft.fftshift(np.exp(-(fx**2.0 + fy**2.0) / s1**2)).astype(np.float32)


def _prefilter(img: np.ndarray, fc: float) -> np.ndarray:
    """Whitening and local contrast normalisation (LEAR `prefilt`), shape preserved."""
    w = 5
    img = np.log1p(img)
    padded = np.pad(img, w, mode="symmetric")
    gf = _prefilter_gauss(padded.shape[0], fc)
    out = padded - np.real(np.fft.ifft2(np.fft.fft2(padded) * gf))
    local = np.sqrt(np.abs(np.real(np.fft.ifft2(np.fft.fft2(out**2) * gf))))
    out = out / (0.2 + local)
    return out[w:-w, w:-w]


def to_gray_square(image: np.ndarray, size: int) -> np.ndarray:
    """uint8 (H, W[, 3]) BGR or grey -> float32 (size, size) grey in [0, 255]."""
    if image.ndim == 3:
        if image.shape[2] != 3:
            raise BadInput(f"Expected an image of shape (H, W) or (H, W, 3), got {image.shape}")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim != 2:
        raise BadInput(f"Expected an image of shape (H, W) or (H, W, 3), got {image.shape}")
    if min(image.shape[:2]) < 16:
        raise BadInput(f"Image too small for GIST: {image.shape}")
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA).astype(np.float32)


def compute_gist(image: np.ndarray, params: GistParams = DEFAULT_PARAMS) -> np.ndarray:
    """GIST descriptor of one image.

    Parameters
    ----------
    image : ndarray of shape (H, W, 3) (BGR) or (H, W), uint8.
    params : the descriptor configuration.

    Returns
    -------
    ndarray of shape (params.dim,), float32, L2-normalised (unit length), so that distance
    thresholds do not depend on image contrast or size.
    """
    img = _prefilter(to_gray_square(image, params.image_size), params.prefilter_fc)
    b = params.boundary
    padded = np.pad(img, b, mode="symmetric")
    spectrum = np.fft.fft2(padded.astype(np.float32))
    filtered = np.multiply(spectrum[None], gabor_bank(params))
    responses = np.fft.ifft2(filtered, axes=(-2, -1))
    s, k = params.image_size, params.blocks
    crop = np.abs(responses[:, b : b + s, b : b + s])
    g = crop.reshape(len(crop), k, s // k, k, s // k).mean(axis=(2, 4))
    # LEAR orders each filter's windows column-major; keep that order for compatibility.
    g = g.transpose(0, 2, 1).reshape(-1).astype(np.float32)
    norm = float(np.linalg.norm(g))
    return g / norm if norm > 0 else g
