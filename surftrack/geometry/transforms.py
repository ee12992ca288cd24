"""SO(3) / SE(3) helpers on numpy arrays.

Rotations are 3x3 matrices, poses 4x4 homogeneous matrices (model-to-camera unless stated), quaternions
are (x, y, z, w) as in scipy and Foxglove. Functions accept a single item or a leading batch dimension.
Rotation conversions are delegated to scipy.spatial.transform; only the SE(3) exponential and logarithm
(the coupled translation part) are written here.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

_EPS = 1e-9


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) from an axis-angle vector (..., 3) in radians."""
    rv = np.asarray(rotvec, dtype=np.float64)
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(rv.shape[:-1] + (3, 3))


def so3_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (..., 3) in radians of a rotation matrix (..., 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about ``axis`` (any non-zero length)."""
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    if n < _EPS:
        raise ValueError("rotation axis must be non-zero")
    return so3_exp(axis / n * angle)


def quat_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) as (x, y, z, w) with w >= 0, from rotation matrices (..., 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(R.shape[:-2] + (4,))


def matrix_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) given as (x, y, z, w); normalised first."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle in degrees between rotations: arccos((tr(R_a R_b^T) - 1) / 2), clipped."""
    tr = np.einsum("...ij,...ij->...", np.asarray(R_a, np.float64), np.asarray(R_b, np.float64))
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 pose(s) from rotation (..., 3, 3) and translation (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_split(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of pose(s) (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, :3].copy(), T[..., :3, 3].copy()


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid pose(s) (..., 4, 4), using R^T rather than a general matrix inverse."""
    R, t = se3_split(T)
    Rt = np.swapaxes(R, -1, -2)
    return se3(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def se3_compose(*Ts: np.ndarray) -> np.ndarray:
    """Product T_1 @ T_2 @ ... of poses, left to right (a_from_b @ b_from_c = a_from_c)."""
    if not Ts:
        return np.eye(4)
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by the pose ``T`` (4, 4): ``x' = R x + t``, the homogeneous product
    ``T @ [x, 1]``. For a pose given as (R, t), pass ``se3(R, t)``."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian V of SO(3) for axis-angle vectors (N, 3), used by the SE(3) exp/log."""
    theta = np.linalg.norm(w, axis=-1)[:, None, None]
    W = np.zeros((w.shape[0], 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W = W - np.swapaxes(W, 1, 2)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + a * W + b * (W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Pose(s) (..., 4, 4) from twist(s) (..., 6) ordered (rho, omega): translation part first."""
    xi = np.asarray(xi, dtype=np.float64)
    flat = xi.reshape(-1, 6)
    R = so3_exp(flat[:, 3:])
    t = np.einsum("nij,nj->ni", _left_jacobian(flat[:, 3:]), flat[:, :3])
    return se3(R, t).reshape(xi.shape[:-1] + (4, 4))


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist(s) (..., 6) ordered (rho, omega) of pose(s) (..., 4, 4); inverse of :func:`se3_exp`."""
    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    w = so3_log(flat[:, :3, :3])
    rho = np.linalg.solve(_left_jacobian(w), flat[:, :3, 3:4])[..., 0]
    return np.concatenate([rho, w], axis=-1).reshape(T.shape[:-2] + (6,))


def slerp(R0: np.ndarray, R1: np.ndarray, s: float | np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between two rotations at fraction(s) s in [0, 1]."""
    rots = Rotation.from_matrix(np.stack([R0, R1]))
    return Slerp([0.0, 1.0], rots)(np.clip(s, 0.0, 1.0)).as_matrix()


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose between T0 (s = 0) and T1 (s = 1): slerp on rotation, linear on translation."""
    R = slerp(T0[:3, :3], T1[:3, :3], s)
    return se3(R, (1.0 - s) * T0[:3, 3] + s * T1[:3, 3])
