"""Training vocabularies from images or robot folders (`fleetmap vocab train`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import numpy as np

from fleetmap.errors import BadInput, BadRobotData
from fleetmap.features import DEFAULT_PARAMS as FEATURE_DEFAULTS
from fleetmap.features import FeatureParams, detect_and_describe
from fleetmap.gist import DEFAULT_PARAMS as GIST_DEFAULTS
from fleetmap.gist import GistParams, compute_gist
from fleetmap.vocabulary import Vocabulary, train_vocabulary

log = logging.getLogger(__name__)
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff"}


def collect_images(inputs: Iterable[str | Path], stride: int = 1) -> list[Path]:
    """Image files from a mix of image paths, image folders and TUM robot folders.

    A robot folder (one with `rgb.txt`) contributes the colour images it lists, every
    `stride`-th; a plain folder every image file in it, sorted.
    """
    out: list[Path] = []
    for item in map(Path, inputs):
        if item.is_file():
            out.append(item)
        elif (item / "rgb.txt").is_file():
            from fleetmap.dataset import read_list

            names = [item / v[0] for _, v in read_list(item / "rgb.txt") if v]
            out += names[::stride]
        elif item.is_dir():
            files = sorted(p for p in item.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            out += files[::stride]
        else:
            raise BadRobotData(f"No such image, folder or robot folder: {item}")
    if not out:
        raise BadInput("No training images found")
    return out


def train_from_images(
    paths: list[Path],
    n_gist_clusters: int = 8,
    n_words: int = 500,
    gist_params: GistParams = GIST_DEFAULTS,
    feature_params: FeatureParams = FEATURE_DEFAULTS,
    seed: int = 0,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
    source: str = "",
) -> Vocabulary:
    """Algorithm 1 on image files: GIST and MSER+SIFT of each, then both k-means."""
    gists, descs = [], []
    for p in progress(paths):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise BadRobotData(f"Cannot read image {p}")
        gists.append(compute_gist(img, gist_params))
        descs.append(detect_and_describe(img, feature_params).descriptors)
    all_desc = np.concatenate(descs).astype(np.float32)
    if len(gists) < n_gist_clusters:
        raise BadInput(f"{len(gists)} images cannot make {n_gist_clusters} GIST clusters")
    if len(all_desc) < n_words:
        raise BadInput(f"{len(all_desc)} descriptors cannot make {n_words} words")
    return train_vocabulary(
        np.stack(gists),
        all_desc,
        n_gist_clusters,
        n_words,
        gist_params,
        seed=seed,
        source=source or f"{len(paths)} images",
    )
