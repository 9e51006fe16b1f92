"""Poses and rigid-transform helpers. `T_a_b` maps points from frame b into frame a.

numpy only: reading a robot's poses is robot-side, and a robot-side install has no SciPy
(143 MB of the 300 MB budget). The quaternion conversions are those of SciPy's `Rotation`
(scalar last, Markley's method from a matrix), which the tests compare them with.
"""

from __future__ import annotations

import numpy as np

from fleetmap.errors import BadInput

#: Largest translation accepted in a pose (metres) and orthonormality tolerance.
MAX_TRANSLATION_M = 1e6
RIGID_TOL = 1e-3


def check_transform(T: np.ndarray, name: str = "transform") -> np.ndarray:
    """Return `T` as float64 of shape (4, 4) if it is a rigid transform (finite, rotation
    orthonormal within 1e-3 with det +1, bottom row 0 0 0 1, translation within 1e6 m);
    raise BadInput naming the problem otherwise."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise BadInput(f"{name} must be a 4x4 matrix of numbers: {exc}") from exc
    if T.shape != (4, 4):
        raise BadInput(f"Expected {name} of shape (4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise BadInput(f"{name} has non-finite values")
    if np.max(np.abs(T[3] - [0, 0, 0, 1])) > 1e-9:
        raise BadInput(f"{name} must have the bottom row 0 0 0 1, got {T[3].tolist()}")
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > RIGID_TOL or np.linalg.det(R) < 0:
        raise BadInput(
            f"{name} must be rigid: its rotation block is not orthonormal with det +1 "
            f"(det {np.linalg.det(R):.3g})"
        )
    if np.max(np.abs(T[:3, 3])) > MAX_TRANSLATION_M:
        raise BadInput(f"{name} translation exceeds {MAX_TRANSLATION_M:g} m")
    return T


def pose_from_tum(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 camera-to-map transform from a TUM line's translation and quaternion (qx qy qz qw)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise BadInput(f"Expected a unit quaternion, got {q.tolist()}")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q / norm)
    T[:3, 3] = t_xyz
    return T


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """Inverse of `pose_from_tum`: array [tx, ty, tz, qx, qy, qz, qw]."""
    return np.concatenate([T[:3, 3], matrix_to_quat(T[:3, :3])])


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of shape (3, 3) of a unit quaternion (qx, qy, qz, qw)."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64)
    return np.array(
        [
            [x * x - y * y - z * z + w * w, 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), -x * x + y * y - z * z + w * w, 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), -x * x - y * y + z * z + w * w],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw) of a rotation matrix of shape (3, 3); a matrix that
    is not quite orthonormal is first replaced by the nearest orthonormal one (SVD)."""
    R = np.asarray(R, dtype=np.float64)
    if np.linalg.det(R) <= 0:
        raise BadInput(f"Expected a rotation matrix (det > 0), got det {np.linalg.det(R):.3g}")
    if not np.allclose(R @ R.T, np.eye(3), rtol=1e-5, atol=1e-12):
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
    # Markley (2008): build from the largest of the diagonal and the trace, for stability
    tr = np.trace(R)
    i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], tr]))
    if i == 3:
        q = [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1 + tr]
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q = np.empty(4)
        q[i] = 1 - tr + 2 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, u: float) -> np.ndarray:
    """The pose a fraction `u` (0 to 1) of the way from T0 to T1: the position along the
    line, the rotation along the shorter arc (spherical interpolation of unit quaternions,
    numpy alone: the robot side has no scipy)."""
    q0, q1 = matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3])
    d = float(q0 @ q1)
    if d < 0:  # q and -q are one rotation: the shorter way round
        q1, d = -q1, -d
    if d > 0.9995:  # nearly one rotation: the line is the arc
        q = q0 + u * (q1 - q0)
    else:
        a = np.arccos(d)
        q = (np.sin((1 - u) * a) * q0 + np.sin(u * a) * q1) / np.sin(a)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q / np.linalg.norm(q))
    T[:3, 3] = (1 - u) * T0[:3, 3] + u * T1[:3, 3]
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points of shape (N, 3) through the 4x4 transform T; returns shape (N, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def residuals(T: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """How far (metres, shape (N,)) T puts each point of X (N, 3) from its match in Y."""
    return np.linalg.norm(apply(T, X) - Y, axis=1)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle in degrees of a 3x3 rotation matrix (numerically safe)."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation error (same unit as T) and rotation error (degrees) between two poses."""
    D = invert(T_true) @ T_est
    return float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D[:3, :3])


def displacement_rms(T_1: np.ndarray, T_2: np.ndarray, points: np.ndarray) -> float:
    """RMS distance (metres) between points (N, 3) moved by T_1 and by T_2: how far apart
    two alignments put a map, whatever its frame's origin. (`transform_error`'s translation
    is measured at the frame's origin: a map 10 m from it turned by 3 degrees moves 0.5 m
    there while its points move a few cm.)"""
    return float(np.sqrt(((apply(T_1, points) - apply(T_2, points)) ** 2).sum(1).mean()))
