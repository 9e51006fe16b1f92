"""The inverted file over visual words beside the GIST clusters, on real data."""

from dataclasses import replace

import numpy as np
import pytest

from fleetmap.frame import encode
from fleetmap.place import CascadeParams, Filter, PlaceDB
from fleetmap.place import postings as postings_module
from fleetmap.place.cascade import run_cascade
from fleetmap.place.index import PlaceIndex
from fleetmap.place.postings import Postings
from tests.conftest import corridor_revisits

# GIST stage that keeps nothing: only the inverted file can nominate
NO_GIST = CascadeParams(gist_threshold=1e-6)


@pytest.fixture(scope="module")
def corridor_index(corridor_frames, vocabulary):
    idx = PlaceIndex(vocabulary.gist_centroids, vocabulary.n_words)
    for i, f in corridor_frames.items():
        idx.add(i, 0, float(i), f.gist, f.bow_ids, f.bow_counts)
    return idx


def test_revisit_the_gist_stage_misses_is_found_through_the_inverted_file(
    corridor, corridor_frames, corridor_index
):
    gt = corridor_revisits(corridor)
    load = corridor_frames.__getitem__
    hits, false = 0, []
    for q in range(41, 85):
        flt = Filter(max_stamp=q - 5.5)
        r = run_cascade(corridor_frames[q], corridor_index, load, NO_GIST, flt)
        names = [s.name for s in r.stages]
        assert names[:3] == ["clusters", "gist_threshold", "inverted_file"]
        assert r.stages[1].kept == 0 and r.stages[2].kept <= NO_GIST.ivf_candidates
        if r.winner is None:
            continue
        if r.winner.stamp in gt.get(q, ()):
            hits += 1
        else:
            false.append((q, r.winner.stamp))
    # the same verification keeps precision; most revisits come back through the words
    assert false == []
    assert hits >= 0.6 * len(gt)
    # without the inverted file the same GIST stage finds nothing
    off = replace(NO_GIST, ivf_candidates=0)
    r = run_cascade(corridor_frames[60], corridor_index, load, off, Filter(max_stamp=54.5))
    assert r.winner is None and r.stages[2].kept == 0


def test_inverted_file_adds_only_what_the_gist_stage_did_not_nominate(
    corridor_frames, corridor_index
):
    q = corridor_frames[60]
    wide = CascadeParams(m_clusters=100, gist_threshold=2.0, max_candidates=10)
    gist_cands, _ = corridor_index.global_stage(q.gist, wide, Filter(max_stamp=54.5))
    known = [c.kf_id for c in gist_cands]
    extra, stage = corridor_index.word_stage(
        (q.bow_ids, q.bow_counts), q.gist, wide, Filter(max_stamp=54.5), known
    )
    assert len(extra) == wide.ivf_candidates and stage.kept == len(known) + len(extra)
    assert not {c.kf_id for c in extra} & set(known)
    assert all(c.stamp < 54.5 for c in extra)
    # highest partial Bhattacharyya first: the BoW stage's distance agrees on the best
    d = corridor_index.bow_distances(q.bow_ids, q.bow_counts, np.array([c.kf_id for c in extra]))
    assert d[0] <= np.median(d)


def test_removing_a_robot_removes_its_postings_and_a_restart_rebuilds_them(
    corridor_frames, vocabulary, tmp_path
):
    db = PlaceDB(tmp_path / "p.sqlite", vocabulary, background=False)
    try:
        for i in range(1, 85):
            robot = "a" if i <= 42 else "b"
            db.add_keyframe(robot, encode(replace(corridor_frames[i], robot_id=robot)))
        idx = db.index
        entries_b = sum(len(corridor_frames[i].bow_ids) for i in range(43, 85))
        before, df_before = len(idx.postings), idx.postings.df.copy()
        q = corridor_frames[70]
        flt = Filter()
        codes = {
            c.robot_code
            for c in idx.word_stage((q.bow_ids, q.bow_counts), q.gist, NO_GIST, flt, [])[0]
        }
        assert db.store.robot_code("b") in codes
        assert db.delete_robot("b") == 42
        assert len(idx.postings) == before - entries_b and idx.postings.n_docs == 42
        df_b = np.zeros(vocabulary.n_words, np.int64)
        for i in range(43, 85):
            df_b[corridor_frames[i].bow_ids] += 1
        assert np.array_equal(idx.postings.df, df_before - df_b)
        after, _ = idx.word_stage((q.bow_ids, q.bow_counts), q.gist, NO_GIST, flt, [])
        assert after and {c.robot_code for c in after} == {db.store.robot_code("a")}
        # the index rebuilt from the store holds the same postings
        again = PlaceDB(db.path, vocabulary, background=False)
        try:
            assert len(again.index.postings) == len(idx.postings)
            assert np.array_equal(again.index.postings.df, idx.postings.df)
            rebuilt, _ = again.index.word_stage((q.bow_ids, q.bow_counts), q.gist, NO_GIST, flt, [])
            assert [c.kf_id for c in rebuilt] == [c.kf_id for c in after]
        finally:
            again.close()
    finally:
        db.close()


def test_postings_score_is_the_partial_bhattacharyya_across_merges_and_removal(monkeypatch):
    monkeypatch.setattr(postings_module, "_MAX_TAIL", 300)  # many segments and merges
    rng = np.random.default_rng(7)
    n_words, bows, pst = 60, [], Postings(60)
    for _ in range(50):
        batch = []
        for _ in range(rng.integers(1, 12)):
            w = np.sort(rng.choice(n_words, rng.integers(1, 20), replace=False))
            batch.append((w, rng.integers(1, 6, len(w))))
        pst.add(
            len(bows),
            np.array([len(w) for w, _ in batch]),
            np.concatenate([w for w, _ in batch]),
            np.concatenate([c for _, c in batch]),
        )
        bows += batch
    assert len(pst.segments) >= 2
    alive = np.ones(len(bows), bool)
    alive[rng.choice(len(bows), len(bows) // 3, replace=False)] = False
    pst.remove(alive)
    q_ids, q_counts = np.array([2, 9, 17, 33, 51]), np.array([3, 1, 2, 1, 4])
    words = pst.informative(q_ids, q_counts, 3)
    assert len(words) == 3 and set(words) <= set(q_ids)
    score = pst.score(q_ids, q_counts, words, len(bows))
    q = dict(zip(q_ids, np.sqrt(q_counts / q_counts.sum()), strict=True))
    for s, (w, c) in enumerate(bows):
        d = dict(zip(w, np.sqrt(c / c.sum()), strict=True))
        ref = sum(q[x] * d[x] for x in words if x in d) if alive[s] else 0.0
        assert score[s] == pytest.approx(ref, abs=2e-3)  # weights stored as float16
    assert len(pst) == sum(len(w) for (w, _), a in zip(bows, alive, strict=True) if a)
