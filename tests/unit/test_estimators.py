"""Transform estimators recover known transforms from correspondences with outliers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetmap.errors import BadInput, NotEnoughCorrespondences
from fleetmap.estimators import AffineEstimator, MLPEstimator, RigidEstimator, SimilarityEstimator
from fleetmap.geometry import transform_error
from fleetmap.registration import kabsch, ransac_rigid


def _random_rigid(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


def _data(rng, T, n=300, noise=0.005, outliers=0.3):
    X = rng.uniform(-2, 2, (n, 3))
    Y = X @ T[:3, :3].T + T[:3, 3] + rng.normal(0, noise, (n, 3))
    bad = rng.random(n) < outliers
    Y[bad] = rng.uniform(-6, 6, (bad.sum(), 3))
    return X, Y, bad


@pytest.mark.parametrize("seed", range(5))
def test_rigid_and_similarity_recover_with_outliers(seed):
    rng = np.random.default_rng(seed)
    T = _random_rigid(rng)
    X, Y, bad = _data(rng, T)
    est = RigidEstimator(threshold=0.03).fit(X, Y)
    dt, dr = transform_error(est.T_, T)
    assert dt < 0.01 and dr < 0.5
    assert (est.inliers_ == ~bad).mean() > 0.97
    S = T.copy()
    S[:3, :3] *= 1.7
    X, Y, _ = _data(rng, S)
    sim = SimilarityEstimator(threshold=0.03).fit(X, Y)
    np.testing.assert_allclose(sim.T_, S, atol=0.02)


@pytest.mark.parametrize("seed", range(3))
def test_affine_recovers_a_shear(seed):
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = rng.uniform(-1, 1, (3, 3)) + 2 * np.eye(3)
    T[:3, 3] = rng.uniform(-3, 3, 3)
    X, Y, _ = _data(rng, T, outliers=0.2)
    est = AffineEstimator(threshold=0.03).fit(X, Y)
    np.testing.assert_allclose(est.T_, T, atol=0.01)
    np.testing.assert_allclose(est.transform(X[:5]), X[:5] @ est.T_[:3, :3].T + est.T_[:3, 3])


def test_vectorised_ransac_rigid_and_kabsch():
    rng = np.random.default_rng(7)
    T = _random_rigid(rng)
    X, Y, bad = _data(rng, T, n=200, outliers=0.6)
    T_est, inl = ransac_rigid(X, Y, 0.03)
    assert transform_error(T_est, T)[0] < 0.01
    assert inl[~bad].mean() > 0.95 and inl[bad].mean() < 0.05
    np.testing.assert_allclose(kabsch(X[~bad], Y[~bad]), T, atol=0.01)


def test_mlp_learns_an_affine_map_to_high_accuracy():
    """The thesis network trained by Levenberg-Marquardt: error far below the noise-free
    figures the thesis printed for an affine map (Table 3.2, T4: 0.0029 units)."""
    rng = np.random.default_rng(0)
    T = np.array([[0.36, 0.48, 0, 100], [0, 0.6, 0, 300], [0.48, 0.64, 0.6, 70], [0, 0, 0, 1]])
    X = rng.uniform(-50, 50, (600, 3))
    Y = X @ T[:3, :3].T + T[:3, 3]
    est = MLPEstimator(hidden=20, max_epochs=200).fit(X[:500], Y[:500])
    err = np.linalg.norm(est.transform(X[500:]) - Y[500:], axis=1).mean()
    assert err < 0.0029
    np.testing.assert_allclose(est.affine_, T, atol=1e-3)
    assert est.stop_reason_ in {"goal", "min_grad", "validation", "max_epochs", "max_mu"}


def test_bad_inputs_are_named():
    with pytest.raises(BadInput, match=r"shape \(N, 3\)"):
        RigidEstimator().fit(np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(NotEnoughCorrespondences, match="at least 3"):
        RigidEstimator().fit(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(BadInput, match="non-finite"):
        RigidEstimator().fit(np.full((5, 3), np.nan), np.zeros((5, 3)))
    flat = np.c_[np.random.default_rng(0).random((20, 2)), np.zeros(20)]
    with pytest.raises(BadInput, match="coplanar"):
        AffineEstimator().fit(flat, flat)


@pytest.mark.parametrize(("n", "model"), [(12, "rigid"), (400, "rigid"), (3000, "affine")])
def test_ransac_draws_its_samples_as_taken_the_same_as_all_up_front(n, model):
    """The usable minimal samples drawn block by block (`_usable_blocks`, session 23) are
    the ones drawing all `iterations` first and filtering gives, in the same order and the
    same blocks of 256: a RANSAC that stops early answers what it answered before."""
    from fleetmap.registration import MODELS, _usable, _usable_blocks

    rng = np.random.default_rng(4)
    X = rng.normal(size=(n, 3))
    Y = X + 0.05 * rng.normal(size=(n, 3))
    k, iterations = MODELS[model][0], 1000
    lazy = list(_usable_blocks(X, Y, k, iterations, np.random.default_rng(7), 0.1, model, 1e-3))
    if n <= 22:
        idx = np.array(np.triu_indices(n, 1)).T
        trip = np.array([(i, j, m) for i, j in idx for m in range(j + 1, n)])
    else:
        draw = np.random.default_rng(7)
        trip = np.stack([draw.choice(n, k, replace=False) for _ in range(iterations)])
    up_front = trip[_usable(X[trip], Y[trip], 0.1, model, 1e-3)]
    assert [len(b) for b in lazy[:-1]] == [256] * (len(lazy) - 1)
    np.testing.assert_array_equal(np.concatenate(lazy), up_front)


def test_choices_are_rng_choice_value_for_value_and_leave_the_generator_as_it_does():
    """`registration._choices` (a block of k-of-n draws at once) gives what one
    `rng.choice(n, k, replace=False)` per draw gives, and leaves the generator where those
    calls leave it (the next draws, of any kind, the same): over seeds, small and large n
    (Floyd's algorithm beyond 10,000 too), blocks of odd and even length (the 32-bit halves
    buffered between calls); and where `rng.choice` itself draws: n = k, 201 of 10,001
    (numpy's tail shuffle) and n = 1.5e9 (where a word is drawn again)."""
    from fleetmap.registration import _choices

    for seed in range(40):
        for n, k in (
            (3, 3),
            (4, 3),
            (5, 4),
            (23, 3),
            (400, 3),
            (3000, 4),
            (12_000, 3),
            (10_001, 201),
        ):
            for count in (1, 7, 64):
                ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
                ref.random()  # a 64-bit draw first, then a 32-bit one: a half buffered
                ours.random()
                ref.integers(1 << 20, dtype=np.uint32)
                ours.integers(1 << 20, dtype=np.uint32)
                want = np.stack([ref.choice(n, k, replace=False) for _ in range(count)])
                np.testing.assert_array_equal(_choices(ours, n, k, count), want)
                np.testing.assert_array_equal(
                    _choices(ours, n, k, 5), [ref.choice(n, k, replace=False) for _ in range(5)]
                )
                assert (
                    ours.integers(1 << 40, size=3).tolist()
                    == ref.integers(1 << 40, size=3).tolist()
                )
    big = 1_500_000_003  # 3 in 10 of the largest bounds' words drawn again
    ours, ref = np.random.default_rng(3), np.random.default_rng(3)
    np.testing.assert_array_equal(
        _choices(ours, big, 3, 64), [ref.choice(big, 3, replace=False) for _ in range(64)]
    )
    assert ours.random() == ref.random()
