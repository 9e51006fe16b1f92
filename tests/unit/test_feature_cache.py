"""`fleetmap.feature_cache`: a keyframe's image features read back from the cache are the
ones extracted afresh, to the bit; an unreadable file is extracted again; other settings
never read another's features."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetmap import extract
from fleetmap.dataset import load_depth, load_rgb, read_recording
from fleetmap.extract import FrameExtractor
from fleetmap.feature_cache import ENV, FeatureCache, Recent

ROBOT = Path(__file__).resolve().parents[2] / "examples" / "fr1_rpy_fleet" / "alpha"


def _frame(x: FrameExtractor, k: int = 3):
    rec = read_recording(ROBOT)
    f = rec.frames[k]
    rgb, depth = load_rgb(f.rgb_path), load_depth(f.depth_path)
    return x("alpha", f.stamp, rgb, depth, rec.intrinsics, f.T_map_cam)


def _same(a, b) -> None:
    for k in a.__dataclass_fields__:
        u, v = getattr(a, k), getattr(b, k)
        if isinstance(u, np.ndarray):
            assert u.dtype == v.dtype and np.array_equal(u, v), k
        else:
            assert u == v, k


def _no_extraction(*args, **kwargs):
    raise AssertionError("features extracted although the cache holds them")


def test_features_read_back_are_the_ones_extracted(vocabulary, tmp_path, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    fresh = _frame(FrameExtractor(vocabulary))
    monkeypatch.setenv(ENV, str(tmp_path))
    first = _frame(FrameExtractor(vocabulary))  # extracted, and kept
    assert len(list(tmp_path.rglob("*.npz"))) == 1
    monkeypatch.setattr(extract, "detect_and_describe", _no_extraction)
    again = _frame(FrameExtractor(vocabulary))  # read back
    _same(fresh, first)
    _same(fresh, again)
    assert fresh.n_features > 50


def test_an_unreadable_or_incomplete_file_is_extracted_again(vocabulary, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV, str(tmp_path))
    fresh = _frame(FrameExtractor(vocabulary))
    (path,) = tmp_path.rglob("*.npz")
    path.write_bytes(b"not a zip")
    again = _frame(FrameExtractor(vocabulary))
    _same(fresh, again)
    with np.load(path, allow_pickle=False) as z:  # replaced by a readable one
        assert np.array_equal(z["descriptors"], fresh.descriptors)
    np.savez(path.with_suffix(""), gist=fresh.gist)  # a file without the features
    _same(fresh, _frame(FrameExtractor(vocabulary)))
    with np.load(path, allow_pickle=False) as z:
        assert np.array_equal(z["bow_ids"], fresh.bow_ids)


def test_other_settings_do_not_read_these_features(vocabulary, tmp_path, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    x = FrameExtractor(vocabulary)
    other = replace(x.feature_params, max_features=x.feature_params.max_features // 2)
    monkeypatch.setenv(ENV, str(tmp_path))
    _frame(FrameExtractor(vocabulary))
    y = FrameExtractor(vocabulary, other)
    assert y.cache.salt != FrameExtractor(vocabulary).cache.salt
    monkeypatch.setattr(extract, "detect_and_describe", _no_extraction)
    with pytest.raises(AssertionError, match="although the cache"):
        _frame(y)


def test_an_unwritable_folder_leaves_extraction_working(vocabulary, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("a file where the cache's folder would be")
    x = FrameExtractor(vocabulary, cache=FeatureCache(blocked, "salt"))
    assert _frame(x).n_features > 50


def test_the_aligners_view_features_read_back_are_the_ones_extracted(tmp_path, monkeypatch):
    """The first look's SIFT and the second look's ASIFT of a view, each by its own
    settings: read back as extracted, and not extracted again."""
    from fleetmap import correspondences
    from fleetmap.align import second_look
    from fleetmap.fleet.view_choice import load_view

    view = load_view(read_recording(ROBOT), 5)
    monkeypatch.setattr(correspondences, "_VIEWS", Recent(0))  # the disk alone
    monkeypatch.delenv(ENV, raising=False)
    fresh = correspondences.view_features(view), second_look._affine(view.rgb, 3, 100)
    monkeypatch.setenv(ENV, str(tmp_path))
    first = correspondences.view_features(view), second_look._affine(view.rgb, 3, 100)
    assert len(list(tmp_path.rglob("*.npz"))) == 2  # two settings, two files
    monkeypatch.setattr(correspondences, "detect_and_describe", _no_extraction)
    monkeypatch.setattr(second_look, "affine_features", _no_extraction)
    again = correspondences.view_features(view), second_look._affine(view.rgb, 3, 100)
    for f in (first, again):
        for a, b in zip(fresh, f, strict=True):
            assert np.array_equal(a.keypoints, b.keypoints)
            assert a.descriptors.dtype == b.descriptors.dtype
            assert np.array_equal(a.descriptors, b.descriptors)
    assert len(fresh[0].keypoints) > 50 and len(fresh[1].keypoints) > 50


def test_a_views_features_asked_again_are_not_extracted_again(monkeypatch):
    """The aligner's recent views (`Recent`): the features of a view met again (the same
    pixels in another view object: another pair, another request) come from memory,
    without the disk cache; another image is extracted."""
    from fleetmap import correspondences
    from fleetmap.fleet.view_choice import load_view

    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setattr(correspondences, "_VIEWS", Recent(4))
    rec = read_recording(ROBOT)
    first = correspondences.view_features(load_view(rec, 5))
    monkeypatch.setattr(correspondences, "detect_and_describe", _no_extraction)
    again = correspondences.view_features(load_view(rec, 5))
    assert np.array_equal(first.descriptors, again.descriptors) and len(first.keypoints) > 50
    with pytest.raises(AssertionError):
        correspondences.view_features(load_view(rec, 6))
