"""SO(3) / SE(3) helpers on numpy arrays.

Rotations are 3x3 matrices, poses 4x4 homogeneous matrices (model-to-camera unless stated), quaternions
are (x, y, z, w) as in scipy and Foxglove. Functions accept a single item or a leading batch dimension.
Quaternion conversions and slerp are delegated to scipy.spatial.transform. The SO(3) exponential and
logarithm are written here in numpy (checked against scipy in the tests): they sit in the inner loops of
the filter, the smoother and the instrument fit, where scipy's per-call overhead (about 40 us) was most
of the instrument fit's time.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

_EPS = 1e-9


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors in plain floats: ``np.cross`` without its axis handling, an order
    of magnitude faster on one pair (for per-part loops of solvers)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices (..., 3, 3) of vectors (..., 3): ``skew(v) @ x == cross(v, x)``."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) from an axis-angle vector (..., 3) in radians (Rodrigues' formula)."""
    rv = np.asarray(rotvec, dtype=np.float64)
    if rv.shape == (3,):  # the common single case without the batch machinery (~5x faster)
        x, y, z = float(rv[0]), float(rv[1]), float(rv[2])
        th2 = x * x + y * y + z * z
        if th2 < 1e-8:
            a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
        else:
            th = math.sqrt(th2)
            a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
        return np.array([[1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
                         [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
                         [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)]])
    v = rv.reshape(-1, 3)
    th2 = np.einsum("ni,ni->n", v, v)
    th = np.sqrt(th2)
    small = th < 1e-4
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)  # sin(t) / t
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / safe**2)  # (1 - cos(t)) / t^2
    S = skew(v)
    R = np.eye(3) + a[:, None, None] * S + b[:, None, None] * (S @ S)
    return R.reshape(rv.shape[:-1] + (3, 3))


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s right Jacobian (3, 3) at ``phi`` (3,): ``exp(phi + d) = exp(phi) exp(J_r(phi) d)`` to first
    order."""
    th = float(np.linalg.norm(phi))
    S = skew(phi)
    if th < 1e-6:
        return np.eye(3) - 0.5 * S
    return np.eye(3) - (1 - np.cos(th)) / th**2 * S + (th - np.sin(th)) / th**3 * S @ S


def so3_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (..., 3) in radians, angle in [0, pi], of a rotation matrix (..., 3, 3); through
    the unit quaternion (Shepperd's method), which stays accurate near 0 and near pi."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        return _so3_log_one(R)
    M = R.reshape(-1, 3, 3)
    if len(M) <= 16:  # a few matrices: the plain-float path per matrix is faster than the batch one
        return np.array([_so3_log_one(m) for m in M]).reshape(R.shape[:-2] + (3,))
    d = np.stack([M[:, 0, 0], M[:, 1, 1], M[:, 2, 2]], axis=1)
    tr = d.sum(axis=1)
    q = np.empty((len(M), 4))  # x, y, z, w
    k = np.argmax(np.c_[d, tr], axis=1)  # the largest of the four squared components, computed directly
    for i in range(3):
        sel = k == i
        if sel.any():
            m, j, l = M[sel], (i + 1) % 3, (i + 2) % 3
            r = np.sqrt(np.maximum(1.0 + 2.0 * m[:, i, i] - tr[sel], 0.0))
            qi = np.empty((sel.sum(), 4))
            qi[:, i] = 0.5 * r
            qi[:, j] = (m[:, j, i] + m[:, i, j]) / (2.0 * r)
            qi[:, l] = (m[:, l, i] + m[:, i, l]) / (2.0 * r)
            qi[:, 3] = (m[:, l, j] - m[:, j, l]) / (2.0 * r)
            q[sel] = qi
    sel = k == 3
    if sel.any():
        m = M[sel]
        r = np.sqrt(np.maximum(1.0 + tr[sel], 0.0))
        q[sel, 3] = 0.5 * r
        q[sel, 0] = (m[:, 2, 1] - m[:, 1, 2]) / (2.0 * r)
        q[sel, 1] = (m[:, 0, 2] - m[:, 2, 0]) / (2.0 * r)
        q[sel, 2] = (m[:, 1, 0] - m[:, 0, 1]) / (2.0 * r)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)  # w >= 0: the angle in [0, pi]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v, w = q[:, :3], q[:, 3]
    n = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(n, w)
    scale = np.where(n < 1e-12, 2.0 / np.maximum(w, 1e-12), angle / np.maximum(n, 1e-300))
    return (v * scale[:, None]).reshape(R.shape[:-2] + (3,))


def _so3_log_one(R: np.ndarray) -> np.ndarray:
    """:func:`so3_log` of one matrix, in plain floats (the same method)."""
    m = R.tolist()
    d = (m[0][0], m[1][1], m[2][2])
    tr = d[0] + d[1] + d[2]
    k = max(range(4), key=lambda i: (d + (tr,))[i])
    q = [0.0, 0.0, 0.0, 0.0]
    if k == 3:
        r = math.sqrt(max(1.0 + tr, 0.0))
        q = [(m[2][1] - m[1][2]) / (2 * r), (m[0][2] - m[2][0]) / (2 * r), (m[1][0] - m[0][1]) / (2 * r), 0.5 * r]
    else:
        i, j, l = k, (k + 1) % 3, (k + 2) % 3
        r = math.sqrt(max(1.0 + 2.0 * m[i][i] - tr, 0.0))
        q[i], q[j], q[l] = 0.5 * r, (m[j][i] + m[i][j]) / (2 * r), (m[l][i] + m[i][l]) / (2 * r)
        q[3] = (m[l][j] - m[j][l]) / (2 * r)
    if q[3] < 0:
        q = [-c for c in q]
    nq = math.sqrt(sum(c * c for c in q))
    x, y, z, w = (c / nq for c in q)
    n = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 / max(w, 1e-12) if n < 1e-12 else 2.0 * math.atan2(n, w) / n
    return np.array([x * scale, y * scale, z * scale])


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
