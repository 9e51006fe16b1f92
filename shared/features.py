"""Local features: MSER regions described by SIFT (OpenCV), capped per frame.

MSER gives stable, repeatable regions; SIFT describes each at a scale set from the region's
size. Where MSER finds too few regions (texture-poor views), SIFT's own DoG detector tops
the set up. Descriptors are kept as uint8, which is lossless: OpenCV's SIFT quantises
every component to 0..255.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fleetmap.errors import BadInput

SIFT_SIGMA = 1.6
SIFT_LAYERS = 3


@dataclass(frozen=True)
class FeatureParams:
    """Detector settings. `max_features` caps the set; the strongest are kept."""

    max_features: int = 300
    min_mser_features: int = 100
    mser_delta: int = 3
    mser_min_area: int = 30
    mser_max_area_fraction: float = 0.02
    mser_max_variation: float = 0.5
    mser_min_diversity: float = 0.1
    region_scale: float = 0.5  # SIFT keypoint size = region diameter * this
    dedupe_px: float = 3.0


DEFAULT_PARAMS = FeatureParams()


@dataclass(frozen=True)
class LocalFeatures:
    """Keypoint positions of shape (N, 2) float32 (x, y pixels) and descriptors (N, 128) uint8."""

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def _gray(image: np.ndarray) -> np.ndarray:
    if image.dtype != np.uint8:
        raise BadInput(f"Expected a uint8 image, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 2:
        return image
    raise BadInput(f"Expected an image of shape (H, W) or (H, W, 3), got {image.shape}")


def _pack_octaves(sizes: np.ndarray, max_octave: int) -> np.ndarray:
    """OpenCV's packed (octave, layer) for keypoints of these sizes (N,), so SIFT samples
    the pyramid level that matches each region instead of a huge window at full
    resolution."""
    s = np.maximum(sizes / (2.0 * SIFT_SIGMA), 1.0)
    e = np.minimum(np.log2(s), max_octave + (SIFT_LAYERS - 1) / SIFT_LAYERS)
    octave = np.floor(e).astype(np.int64)
    layer = np.clip(np.round((e - octave) * SIFT_LAYERS), 0, SIFT_LAYERS - 1).astype(np.int64)
    return (octave & 255) | (layer << 8)


def _mser_keypoints(gray: np.ndarray, p: FeatureParams) -> list[cv2.KeyPoint]:
    max_area = int(p.mser_max_area_fraction * gray.shape[0] * gray.shape[1])
    mser = cv2.MSER_create(
        delta=p.mser_delta,
        min_area=p.mser_min_area,
        max_area=max(max_area, p.mser_min_area + 1),
        max_variation=p.mser_max_variation,
    )
    mser.setMinDiversity(p.mser_min_diversity)
    regions, _ = mser.detectRegions(gray)
    if not regions:
        return []
    # Centroid and equivalent-circle diameter of every region in one vectorised pass.
    counts = np.array([len(r) for r in regions])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pix = np.concatenate(regions).astype(np.float64)
    centres = np.add.reduceat(pix, starts, axis=0) / counts[:, None]
    diam = 2.0 * np.sqrt(counts / np.pi)
    return [
        cv2.KeyPoint(float(x), float(y), float(max(d * p.region_scale, 4.0)))
        for (x, y), d in zip(centres, diam, strict=True)
    ]


def _strength(gray: np.ndarray, kps: list[cv2.KeyPoint]) -> np.ndarray:
    """Corner strength (minimum eigenvalue of the structure tensor) at each keypoint."""
    eig = cv2.cornerMinEigenVal(gray, blockSize=7, ksize=3)
    h, w = gray.shape
    xy = np.array([k.pt for k in kps]).reshape(-1, 2)
    x = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    return eig[y, x]


def _dedupe(kps: list[cv2.KeyPoint], strength: np.ndarray, radius: float) -> list[int]:
    """Strongest-first non-maximum suppression of nested regions with near-equal centres
    and sizes (MSER reports a region at several nearly identical thresholds)."""
    order = np.argsort(-strength, kind="stable")
    xy = np.array([k.pt for k in kps])
    size = np.array([k.size for k in kps])
    cell = {}
    keep = []
    for i in order:
        key = (int(xy[i, 0] // radius), int(xy[i, 1] // radius))
        near = [
            j
            for dx in (-1, 0, 1)
            for dy in (-1, 0, 1)
            for j in cell.get((key[0] + dx, key[1] + dy), [])
        ]
        if any(
            np.hypot(*(xy[i] - xy[j])) < radius and abs(np.log(size[i] / size[j])) < 0.3
            for j in near
        ):
            continue
        cell.setdefault(key, []).append(i)
        keep.append(int(i))
    return keep


def detect_and_describe(image: np.ndarray, params: FeatureParams = DEFAULT_PARAMS) -> LocalFeatures:
    """MSER+SIFT features of one image, at most `params.max_features`, strongest first.

    Parameters
    ----------
    image : ndarray of shape (H, W, 3) BGR or (H, W), uint8.

    Returns
    -------
    LocalFeatures with keypoints (N, 2) float32 and descriptors (N, 128) uint8.
    """
    gray = _gray(image)
    kps = _mser_keypoints(gray, params)
    if kps:
        strength = _strength(gray, kps)
        keep = _dedupe(kps, strength, params.dedupe_px)
        kps = [kps[i] for i in keep[: params.max_features]]
    if len(kps) < params.min_mser_features:
        kps += _sift_topup(gray, kps, params.max_features - len(kps))
    max_octave = max(int(np.log2(min(gray.shape))) - 5, 0)
    octaves = _pack_octaves(np.array([k.size for k in kps]), max_octave)
    for k, o in zip(kps, octaves.tolist(), strict=True):
        k.octave = o
    sift = cv2.SIFT_create(nOctaveLayers=SIFT_LAYERS, sigma=SIFT_SIGMA)
    kps, desc = sift.compute(gray, kps) if kps else ([], None)
    if desc is None or len(kps) == 0:
        return LocalFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
    xy = np.array([k.pt for k in kps], dtype=np.float32)
    return LocalFeatures(xy, np.clip(np.round(desc), 0, 255).astype(np.uint8))


def _sift_topup(gray: np.ndarray, existing: list[cv2.KeyPoint], n: int) -> list[cv2.KeyPoint]:
    """Up to n SIFT (DoG) keypoints, strongest first, away from existing ones."""
    if n <= 0:
        return []
    # Detect on the half-resolution image: SIFT's own 2x upsampled first octave would cost
    # more than the whole rest of the frame; a fallback needs no sub-pixel-scale blobs.
    half = cv2.pyrDown(gray)
    det = cv2.SIFT_create(nfeatures=2 * n, nOctaveLayers=SIFT_LAYERS, sigma=SIFT_SIGMA)
    cand = sorted(det.detect(half, None), key=lambda k: -k.response)
    taken = np.array([k.pt for k in existing]).reshape(-1, 2)
    out = []
    for k in cand:
        x, y = 2.0 * k.pt[0], 2.0 * k.pt[1]
        if len(taken) and np.min(np.hypot(taken[:, 0] - x, taken[:, 1] - y)) < 3.0:
            continue
        out.append(cv2.KeyPoint(x, y, 2.0 * k.size))
        if len(out) >= n:
            break
    return out


def affine_features(image: np.ndarray, max_tilt: int = 4, per_view: int = 200) -> LocalFeatures:
    """Affine-simulated SIFT (ASIFT, Morel and Yu 2009, OpenCV's `AffineFeature`): SIFT on
    the image seen under simulated camera tilts below `max_tilt` (1, 1.4, 2, 2.8: about 18
    views), `per_view` strongest each. It matches surfaces seen from far apart directions
    where SIFT's own invariance ends (a room walked through the other way). Keypoints in
    the original image; descriptors uint8."""
    gray = _gray(image)
    backend = cv2.SIFT_create(nfeatures=per_view, nOctaveLayers=SIFT_LAYERS, sigma=SIFT_SIGMA)
    kps, desc = cv2.AffineFeature_create(backend, maxTilt=max_tilt).detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        return LocalFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
    xy = np.array([k.pt for k in kps], dtype=np.float32)
    return LocalFeatures(xy, np.clip(np.round(desc), 0, 255).astype(np.uint8))
