"""`fleetmap.matching.mutual_best` answers as `S.argmax(0)[best] == rows`, ties included
(integer descriptors give integer distances: rows tie on a column's maximum)."""

from __future__ import annotations

import numpy as np
import pytest

from fleetmap import matching
from fleetmap.matching import distinct_second, match_descriptors_at, mutual_best


def test_mutual_best_is_argmax_down_the_columns_with_ties():
    rng = np.random.default_rng(3)
    for _ in range(200):
        n, m = rng.integers(2, 40, size=2)
        S = rng.integers(0, 6, size=(n, m)).astype(np.float32)  # many ties
        rows = np.arange(n)
        best = S.argmax(1)
        assert (mutual_best(S, rows, best) == (S.argmax(0)[best] == rows)).all()


def _matches_from_the_whole_matrix(da, db, ratio):
    """The definition: ratio test on each row's two nearest, mutual by argmax down the
    columns of the full distance matrix (first row on ties)."""
    D = ((da[:, None, :].astype(np.float64) - db[None, :, :]) ** 2).sum(2)
    rows = np.arange(len(da))
    best = D.argmin(1)
    d1 = D[rows, best]
    D2 = D.copy()
    D2[rows, best] = np.inf
    d2 = D2.min(1)
    keep = (d1 < ratio**2 * d2) & (D.argmin(0)[best] == rows)
    ia = np.flatnonzero(keep)
    return ia, best[ia]


def test_blocked_matching_is_the_whole_matrix_matching(monkeypatch):
    """Integer descriptors of few levels (many ties between rows and columns), sizes over
    several blocks of the similarity matrix."""
    monkeypatch.setattr(matching, "_BLOCK", 7)
    rng = np.random.default_rng(5)
    for _ in range(60):
        n, m = rng.integers(2, 40, size=2)
        da = rng.integers(0, 3, size=(n, 4)).astype(np.float32)
        db = rng.integers(0, 3, size=(m, 4)).astype(np.float32)
        found = match_descriptors_at(da, db, (0.8, 1.0))
        for ratio, (ia, ib) in zip((0.8, 1.0), found, strict=True):
            ja, jb = _matches_from_the_whole_matrix(da, db, ratio)
            assert np.array_equal(ia, ja) and np.array_equal(ib, jb)


def test_torch_products_give_the_whole_matrix_matching(monkeypatch):
    """The torch product path (torch installed) on uint8 descriptors over the whole 0-255
    range, with ties and several blocks: the same matches as the definition."""
    if matching._torch() is None:
        pytest.skip("torch is not installed (a robot's install): numpy's product is used")
    monkeypatch.setattr(matching, "_BLOCK", 7)
    monkeypatch.setattr(matching, "TORCH_MIN_ENTRIES", 1)
    rng = np.random.default_rng(6)
    for _ in range(60):
        n, m = rng.integers(2, 40, size=2)
        levels = rng.choice([0, 1, 2, 127, 128, 254, 255], size=(n + m, 6))
        da, db = levels[:n].astype(np.uint8), levels[n:].astype(np.uint8)
        assert matching._products(da, db) is not None
        found = match_descriptors_at(da, db, (0.8, 1.0))
        for ratio, (ia, ib) in zip((0.8, 1.0), found, strict=True):
            ja, jb = _matches_from_the_whole_matrix(da, db, ratio)
            assert np.array_equal(ia, ja) and np.array_equal(ib, jb)


@pytest.mark.parametrize("length", [128, 258])
def test_torch_products_are_exact_at_the_extremes(monkeypatch, length):
    """The 8-bit product's shift and corrections hold to the integer for SIFT's 128 and the
    longest descriptors (258) at both ends of the range: 0 . 255, 255 . 255, 128 . 127."""
    if matching._torch() is None:
        pytest.skip("torch is not installed (a robot's install): numpy's product is used")
    monkeypatch.setattr(matching, "TORCH_MIN_ENTRIES", 1)
    rng = np.random.default_rng(7)
    ends = np.array([0, 255, 128, 127], np.uint8)
    da = np.concatenate([np.repeat(ends[:, None], length, 1), rng.integers(0, 256, (5, length))])
    db = np.concatenate([np.repeat(ends[:, None], length, 1), rng.integers(0, 256, (6, length))])
    da, db = da.astype(np.uint8), db.astype(np.uint8)
    S = matching._products(da, db)(slice(0, len(da)))
    assert S.dtype == np.float32
    assert np.array_equal(S.astype(np.int64), da.astype(np.int64) @ db.astype(np.int64).T)


def _distinct_from_the_whole_matrix(da, db, kb, radius, ratio):
    """The definition: the second nearest is the nearest b whose keypoint lies at least
    `radius` from the nearest's."""
    D = ((da[:, None, :].astype(np.float64) - db[None, :, :]) ** 2).sum(2)
    rows = np.arange(len(da))
    best = D.argmin(1)
    far = np.linalg.norm(kb[None, :, :] - kb[best][:, None, :], axis=2) >= radius
    d2 = np.where(far, D, np.inf).min(1)
    keep = (D[rows, best] < ratio**2 * d2) & (D.argmin(0)[best] == rows)
    ia = np.flatnonzero(keep)
    return ia, best[ia]


@pytest.mark.parametrize("torch_path", [False, True])
def test_the_second_nearest_is_another_point(monkeypatch, torch_path):
    """`near` (`distinct_second`): the ratio test's second nearest skips b's features
    within r pixels of the nearest's keypoint (one point described under several tilts),
    on both product paths and over several blocks; the same as the definition, and a match
    the plain ratio test refuses for a near-duplicate is kept."""
    if torch_path and matching._torch() is None:
        pytest.skip("torch is not installed (a robot's install): numpy's product is used")
    monkeypatch.setattr(matching, "_BLOCK", 7)
    monkeypatch.setattr(matching, "TORCH_MIN_ENTRIES", 1 if torch_path else 10**12)
    rng = np.random.default_rng(7)
    for _ in range(60):
        n, m = rng.integers(2, 40, size=2)
        da = rng.integers(0, 256, size=(n, 8)).astype(np.uint8)
        db = rng.integers(0, 256, size=(m, 8)).astype(np.uint8)
        kb = rng.uniform(0, 20, size=(m, 2))
        # (0.83: no distance ratio lands on its square exactly, where float32 and float64
        # may round the comparison apart)
        ((ia, ib),) = match_descriptors_at(da, db, (0.83,), distinct_second(kb, 4.0))
        ja, jb = _distinct_from_the_whole_matrix(da, db, kb, 4.0, 0.83)
        assert np.array_equal(ia, ja) and np.array_equal(ib, jb)
    # one point of b described twice (descriptors as near, keypoints 1 px apart), another
    # point far: the plain test finds the duplicate second and refuses, `near` keeps it
    da = np.array([[100, 100, 100, 100], [250, 250, 250, 250]], np.uint8)
    db = np.array([[100, 100, 100, 101], [100, 100, 100, 99], [0, 0, 0, 0]], np.uint8)
    kb = np.array([[10.0, 10.0], [11.0, 10.0], [50.0, 50.0]])
    assert len(match_descriptors_at(da, db, (0.8,))[0][0]) == 0
    ((ia, ib),) = match_descriptors_at(da, db, (0.8,), distinct_second(kb, 4.0))
    assert ia.tolist() == [0] and ib.tolist() == [0]


def test_asift_copies_of_a_point_no_longer_refuse_its_match(hololens):
    """The second look's matches on a room walked the other way (HoloLens hl_a 80-140
    against hl_b 0-60, 6 x 6 views as it takes them): with the second nearest taken among
    other points, several times as many agree with the truth (3 -> 13 when measured), and
    no smaller a share of them."""
    from fleetmap.align.second_look import affine_matches
    from fleetmap.align.types import SecondLook
    from fleetmap.dataset import read_recording
    from fleetmap.fleet.view_choice import load_view
    from fleetmap.geometry import apply

    T_a_b = np.loadtxt(hololens / "T_a_b.txt")
    ra, rb = read_recording(hololens / "hl_a"), read_recording(hololens / "hl_b")
    va = [load_view(ra, i) for i in np.linspace(80, 139, 6).round().astype(int)]
    vb = [load_view(rb, i) for i in np.linspace(0, 59, 6).round().astype(int)]
    pairs = list(zip(va, vb, strict=True))  # affine_matches takes every view of each side
    counts = {}
    for apart in (0.0, 4.0):
        C = affine_matches(pairs, 0, SecondLook(distinct_px=apart))
        near = np.linalg.norm(apply(T_a_b, C.X) - C.Y, axis=1) < 0.08
        counts[apart] = int(near.sum()), len(C)
    (plain, n_plain), (apart, n_apart) = counts[0.0], counts[4.0]
    assert apart >= max(2 * plain, 8), counts
    assert apart / n_apart >= 0.9 * plain / n_plain, counts


def test_single_threaded_products_change_only_their_own_thread():
    """The second look's matching threads take torch's products on one core each; the
    thread that asked, and every thread started later, keep their count (what
    `torch.set_num_threads` would not: it sets later threads' count as well)."""
    from concurrent.futures import ThreadPoolExecutor

    torch = matching._torch()
    if torch is None:
        pytest.skip("torch is not installed (a robot's install): numpy's product is used")
    here, before = torch.get_num_threads(), _in_a_new_thread(torch.get_num_threads)
    _in_a_new_thread(lambda: torch.set_num_threads(2))  # a count one thread differs from
    try:
        with ThreadPoolExecutor(1, initializer=matching.single_threaded_products) as ex:
            inside = ex.submit(torch.get_num_threads).result()
        assert inside == 1
        assert _in_a_new_thread(torch.get_num_threads) == 2
        assert torch.get_num_threads() == here
    finally:
        _in_a_new_thread(lambda: torch.set_num_threads(before))


def _in_a_new_thread(fn):
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1) as ex:
        return ex.submit(fn).result()
