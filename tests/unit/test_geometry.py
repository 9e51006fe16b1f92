"""Quaternion conversions in numpy (a robot-side install has no SciPy), checked against
SciPy's `Rotation`, which the server side still has."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetmap.errors import BadInput
from fleetmap.geometry import matrix_to_quat, pose_from_tum, pose_to_tum, quat_to_matrix


def _rotations(n: int, seed: int = 0) -> list[np.ndarray]:
    """Random rotations plus the half turns about each axis and the identity, so every
    branch of Markley's method (largest diagonal entry or trace) is taken."""
    Rs = list(Rotation.random(n, random_state=seed).as_matrix())
    return Rs + [np.diag(d) for d in ([1, -1, -1], [-1, 1, -1], [-1, -1, 1], [1, 1, 1])]


def test_quaternion_to_matrix_matches_scipy():
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-15)


def test_matrix_to_quaternion_matches_scipy_sign_included():
    for R in _rotations(300):
        np.testing.assert_allclose(matrix_to_quat(R), Rotation.from_matrix(R).as_quat(), atol=1e-15)


def test_a_not_quite_orthonormal_matrix_is_projected_as_scipy_does():
    rng = np.random.default_rng(2)
    for R in _rotations(100, seed=3):
        noisy = R + rng.normal(scale=1e-4, size=(3, 3))
        expected = Rotation.from_matrix(noisy).as_quat()
        np.testing.assert_allclose(matrix_to_quat(noisy), expected, atol=1e-12)


def test_tum_pose_round_trip_and_errors():
    rng = np.random.default_rng(4)
    for R in _rotations(50, seed=5):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
        v = pose_to_tum(T)
        np.testing.assert_allclose(pose_from_tum(v[:3], v[3:]), T, atol=1e-14)
    with pytest.raises(BadInput, match="det > 0"):
        matrix_to_quat(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(BadInput, match="unit quaternion"):
        pose_from_tum([0, 0, 0], [0, 0, 0, 0])


def test_interpolate_pose_is_scipys_slerp_and_a_line():
    """`geometry.interpolate_pose` (numpy alone, for the robot side) against scipy's Slerp:
    the rotation on the shorter arc, the position on the line, the ends exact."""
    from scipy.spatial.transform import Rotation, Slerp

    from fleetmap.geometry import interpolate_pose

    rng = np.random.default_rng(7)
    for _ in range(20):
        R = Rotation.random(2, random_state=rng)
        T0, T1 = np.eye(4), np.eye(4)
        T0[:3, :3], T1[:3, :3] = R.as_matrix()
        T0[:3, 3], T1[:3, 3] = rng.normal(size=(2, 3))
        for u in (0.0, 0.3, 1.0):
            T = interpolate_pose(T0, T1, u)
            np.testing.assert_allclose(T[:3, :3], Slerp([0, 1], R)([u]).as_matrix()[0], atol=1e-9)
            np.testing.assert_allclose(T[:3, 3], (1 - u) * T0[:3, 3] + u * T1[:3, 3])
    near = T0.copy()
    near[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec([0, 0, 1e-4]).as_matrix()
    half = interpolate_pose(T0, near, 0.5)  # nearly one rotation: the line, normalised
    np.testing.assert_allclose(half[:3, :3] @ half[:3, :3].T, np.eye(3), atol=1e-12)
