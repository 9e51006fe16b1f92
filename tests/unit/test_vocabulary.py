import numpy as np
import pytest

from fleetmap.errors import BadInput, BadVocabulary
from fleetmap.features import detect_and_describe
from fleetmap.gist import GistParams
from fleetmap.training import collect_images, train_from_images
from fleetmap.vocabulary import Vocabulary, bhattacharyya, load_vocabulary
from tests.conftest import imread


def test_default_vocabulary_loads(vocabulary):
    assert vocabulary.gist_centroids.shape == (8, 384)
    assert vocabulary.word_centroids.shape == (500, 128)
    assert len(vocabulary.vocab_id) == 16


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    v = Vocabulary(rng.random((4, 384)), rng.random((20, 128)) * 255, GistParams(), "test")
    v.save(tmp_path / "v.npz")
    w = Vocabulary.load(tmp_path / "v.npz")
    np.testing.assert_array_equal(v.gist_centroids, w.gist_centroids)
    np.testing.assert_array_equal(v.word_centroids, w.word_centroids)
    assert (w.gist_params, w.source, w.vocab_id) == (v.gist_params, "test", v.vocab_id)


def test_a_vocabulary_is_written_at_the_name_given(tmp_path):
    """`vocab train -o my.voc` printed `-> my.voc` and wrote `my.voc.npz` (numpy's suffix);
    a later `--vocab my.voc` then read whatever else had that name."""
    rng = np.random.default_rng(3)
    v = Vocabulary(rng.random((4, 384)), rng.random((20, 128)) * 255, GistParams(), "test")
    v.save(tmp_path / "my.voc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["my.voc"]
    assert Vocabulary.load(tmp_path / "my.voc").vocab_id == v.vocab_id
    with pytest.raises(IsADirectoryError):
        v.save(tmp_path)


def test_bad_files_are_rejected(tmp_path):
    with pytest.raises(BadVocabulary, match="Cannot read"):
        load_vocabulary(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", format=np.array("something-else"))
    with pytest.raises(BadVocabulary, match="not a fleetmap vocabulary"):
        load_vocabulary(tmp_path / "other.npz")
    # object arrays would need pickle: refused
    np.savez(tmp_path / "pickled.npz", format=np.array([{"a": 1}], dtype=object))
    with pytest.raises(BadVocabulary):
        load_vocabulary(tmp_path / "pickled.npz")


def test_bhattacharyya_properties():
    ids = np.array([1, 5, 9], np.uint32)
    c = np.array([3, 1, 2], np.uint16)
    assert bhattacharyya(ids, c, ids, c) == pytest.approx(0.0, abs=1e-6)
    assert bhattacharyya(ids, c, ids, 2 * c) == pytest.approx(0.0, abs=1e-6)  # scale-free
    assert bhattacharyya(ids, c, np.array([2], np.uint32), np.array([4], np.uint16)) == 1.0
    other = (np.array([1, 9, 11], np.uint32), np.array([1, 1, 1], np.uint16))
    d = bhattacharyya(ids, c, *other)
    assert 0 < d < 1 and d == pytest.approx(bhattacharyya(*other, ids, c))


def test_bow_of_a_revisit_is_closer_than_of_another_place(corridor, vocabulary):
    def bow(i):
        return vocabulary.bow(
            detect_and_describe(imread(corridor / "images" / f"{i}.jpg")).descriptors
        )

    # gt_loop_pairs: 60 revisits 18-22; 35 is elsewhere on the loop
    assert bhattacharyya(*bow(60), *bow(20)) < bhattacharyya(*bow(60), *bow(35))


def test_training_from_a_robot_folder(sun3d, tmp_path):
    paths = collect_images([sun3d / "robot_a"], stride=5)
    assert len(paths) == 10
    v = train_from_images(paths, n_gist_clusters=3, n_words=50)
    v.save(tmp_path / "site.npz")
    assert Vocabulary.load(tmp_path / "site.npz").vocab_id == v.vocab_id
    ids, counts = v.bow(detect_and_describe(imread(paths[0])).descriptors)
    assert ids.max() < 50 and counts.sum() > 100


def test_words_agree_with_faiss_on_real_descriptors(corridor, sun3d, vocabulary):
    """Word assignment is numpy brute force (no faiss on a robot): the same words as faiss's
    exact L2 index on real SIFT, and a word is never farther than faiss's choice."""
    import faiss

    index = faiss.IndexFlatL2(128)
    index.add(vocabulary.word_centroids)
    paths = sorted((corridor / "images").glob("*.jpg"))[::4]
    paths += sorted((sun3d / "robot_a" / "rgb").glob("*.png"))[::5]
    total = 0
    for path in paths:
        d = detect_and_describe(imread(path)).descriptors
        ours = vocabulary.words(d)
        _, theirs = index.search(d.astype(np.float32), 1)
        np.testing.assert_array_equal(ours, theirs[:, 0], err_msg=str(path))
        total += len(d)
    assert total > 5000


def test_words_is_the_nearest_word_and_checks_its_input():
    rng = np.random.default_rng(7)
    v = Vocabulary(rng.random((2, 384)), rng.random((50, 128)) * 255, GistParams())
    d = rng.integers(0, 256, (200, 128)).astype(np.uint8)
    dist = ((d[:, None, :].astype(np.float64) - v.word_centroids[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(v.words(d), dist.argmin(1))
    assert v.words(np.zeros((0, 128), np.uint8)).shape == (0,)
    with pytest.raises(BadInput, match=r"shape \(N, 128\), got \(3, 64\)"):
        v.words(np.zeros((3, 64), np.uint8))
