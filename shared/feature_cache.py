"""A keyframe's image features kept on disk by the pixels they came from (opt-in).

GIST, MSER + SIFT and the bag of words depend on the colour image, the detector settings
and the vocabulary only, not on depth or pose; they are most of a keyframe's extraction
(MSER alone about 60 %). A merge run again on the same robots (other parameters, one robot
more, a drifted copy of the same images) reads them back instead (as hloc keeps its
features in a file beside the images). Depth, the pose and everything made from them are
computed every time.

The aligner's views are cached the same way (their SIFT for the first look, ASIFT for the
second: `cached`), by their own settings. On with `FLEETMAP_FEATURE_CACHE=DIR` (or
`FeatureCache(DIR, ...)`). One file a keyframe
(`.npz`, no pickle), named by a digest of the image's pixels and shape and of everything
else the features depend on (this package's version, the detector and GIST settings, the
vocabulary's id), so other settings never read another's features. A file that cannot be
read is computed again and replaced; writes are atomic (a process or a thread may write
the same key at once). Nothing is ever deleted: the folder is the user's to clear.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

ENV = "FLEETMAP_FEATURE_CACHE"


class FeatureCache:
    """Features by image under `root`; `salt`: what else they depend on (`salt_of`)."""

    def __init__(self, root, salt: str):
        self.root, self.salt = Path(root), salt

    @classmethod
    def from_env(cls, salt: str) -> FeatureCache | None:
        """The cache `$FLEETMAP_FEATURE_CACHE` names, or None where it is unset or empty."""
        root = os.environ.get(ENV, "").strip()
        return cls(root, salt) if root else None

    def key(self, image: np.ndarray) -> str:
        return digest(image, self.salt)

    def get(self, key: str, fields: tuple[str, ...]) -> dict[str, np.ndarray] | None:
        """The arrays `fields` kept under `key`, or None (absent, unreadable, incomplete)."""
        path = self.root / key[:2] / f"{key}.npz"
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in fields}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
            log.warning("feature cache: %s unreadable (%s): computed again", path, e)
            return None

    def put(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        folder = self.root / key[:2]
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
        except OSError as e:  # a read-only disk: the run goes on without it
            log.warning("feature cache: cannot write under %s (%s)", folder, e)
            return
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, folder / f"{key}.npz")
        except OSError as e:  # a full disk
            log.warning("feature cache: cannot write under %s (%s)", folder, e)
            Path(tmp).unlink(missing_ok=True)


class Recent:
    """The last `size` results by key, in memory, shared by the aligner's request threads.
    The views of one robot recur in the pairs of a fleet's merge (each robot in two of a
    three-robot fleet's pairs) and in the live map's refits as keyframes arrive: their
    features are then not computed again."""

    def __init__(self, size: int):
        self.size, self._items, self._lock = size, OrderedDict(), threading.Lock()

    def get(self, key, make):
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = make()  # outside the lock: two threads may both compute one, rarely
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value


def digest(image: np.ndarray, salt: str = "") -> str:
    """A digest (hex) of an image's pixels, shape and type, and of `salt`."""
    h = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=20)
    h.update(f"{image.shape}{image.dtype}{salt}".encode())
    return h.hexdigest()


def salt_of(*parts) -> str:
    """What features depend on besides the image: this package's version and `parts`
    (settings dataclasses, the vocabulary's id), as text."""
    from fleetmap import __version__

    return repr((__version__, *parts))


def cached(
    cache: FeatureCache | None, image: np.ndarray, fields: tuple[str, ...], make
) -> dict[str, np.ndarray]:
    """`make()` (the arrays `fields`, computed from `image` alone), or what it gave for the
    same image before, where there is a cache."""
    key = cache.key(image) if cache else None
    found = cache.get(key, fields) if key else None
    if found is not None:
        return found
    out = make()
    if key:
        cache.put(key, out)
    return out


def cached_local(image: np.ndarray, detect, *settings):
    """`detect()`: the `LocalFeatures` of `image` under `settings`, or the ones it gave
    before, where `$FLEETMAP_FEATURE_CACHE` names a cache (the aligner's views)."""
    from fleetmap.features import LocalFeatures

    fields = ("keypoints", "descriptors")

    def make() -> dict:
        f = detect()
        return {"keypoints": f.keypoints, "descriptors": f.descriptors}

    f = cached(FeatureCache.from_env(salt_of(*settings)), image, fields, make)
    return LocalFeatures(f["keypoints"], f["descriptors"])
