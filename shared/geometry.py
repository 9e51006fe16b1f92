"""Poses and rigid-transform helpers. `T_a_b` maps points from frame b into frame a."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

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
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = t_xyz
    return T


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """Inverse of `pose_from_tum`: array [tx, ty, tz, qx, qy, qz, qw]."""
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()])


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points of shape (N, 3) through the 4x4 transform T; returns shape (N, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle in degrees of a 3x3 rotation matrix (numerically safe)."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation error (same unit as T) and rotation error (degrees) between two poses."""
    D = invert(T_true) @ T_est
    return float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D[:3, :3])
