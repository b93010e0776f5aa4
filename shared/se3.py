"""Rigid transforms and quaternions.

Convention (docs/ARCHITECTURE.md): ``T_a_b`` is a 4x4 float64 matrix mapping points
in frame b to frame a, ``p_a = T_a_b @ p_b``; compose ``T_a_c = T_a_b @ T_b_c``.
Quaternions are ``quat_xyzw`` (TUM order, Hamilton convention, unit norm).
All functions are pure: new arrays out, inputs untouched.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import GeometryError

F64 = NDArray[np.float64]

_ORTHO_TOL = 1e-6
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_LAST_ROW_TOL = 1e-9 + 1e-5 * _LAST_ROW
_EYE3 = np.eye(3)
_ORTHO_BOUND = _ORTHO_TOL + 1e-5 * _EYE3


def check_transform(T: ArrayLike, name: str = "T") -> F64:
    """Return ``T`` as a float64 (4, 4) array after checking it is a rigid transform.

    Raises:
        GeometryError: wrong shape, non-finite values, last row not [0 0 0 1], or a
            rotation block that is not orthonormal with determinant +1.
    """
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise GeometryError(f"{name}: expected shape (4, 4), got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise GeometryError(f"{name}: contains non-finite values")
    # np.allclose's test (|a - b| <= atol + 1e-5 |b|) written out: this runs several times a frame
    if not (np.abs(M[3] - _LAST_ROW) <= _LAST_ROW_TOL).all():
        raise GeometryError(f"{name}: last row must be [0 0 0 1], got {M[3]}")
    R = M[:3, :3]
    if not (np.abs(R @ R.T - _EYE3) <= _ORTHO_BOUND).all() or np.linalg.det(R) < 0:
        raise GeometryError(f"{name}: rotation block is not a proper rotation")
    return M


def make_transform(R: ArrayLike, t: ArrayLike) -> F64:
    """Build ``T`` (4, 4) from a rotation (3, 3) and a translation (3,) in metres."""
    R_ = np.asarray(R, dtype=np.float64)
    t_ = np.asarray(t, dtype=np.float64).reshape(-1)
    if R_.shape != (3, 3) or t_.shape != (3,):
        raise GeometryError(f"make_transform: expected R (3, 3) and t (3,), got {R_.shape}, {t_.shape}")
    T = np.eye(4)
    T[:3, :3] = R_
    T[:3, 3] = t_
    return T


def inverse(T: ArrayLike) -> F64:
    """Inverse of a rigid transform: ``T_b_a`` from ``T_a_b`` (closed form, no general inverse);
    ``T`` (4, 4) or a stack (..., 4, 4)."""
    M = np.asarray(T, dtype=np.float64)
    R_t = np.swapaxes(M[..., :3, :3], -1, -2)
    out = np.zeros(M.shape)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -(R_t @ M[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> F64:
    """Map points (N, 3) in frame b to frame a with ``T_a_b``; returns (N, 3)."""
    M = np.asarray(T_a_b, dtype=np.float64)
    P = np.asarray(points_b, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise GeometryError(f"transform_points: expected points (N, 3), got {P.shape}")
    return P @ M[:3, :3].T + M[:3, 3]


def quat_to_rotation(quat_xyzw: ArrayLike) -> F64:
    """Rotation matrix (3, 3) from a quaternion ``(x, y, z, w)``; normalises, rejects zero norm."""
    q = np.asarray(quat_xyzw, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise GeometryError(f"quaternion: expected 4 finite values, got {q}")
    n = np.linalg.norm(q)
    if n < 1e-12:
        raise GeometryError("quaternion: zero norm")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quat(R: ArrayLike) -> F64:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` from a rotation matrix (3, 3).

    Shepperd's method: picks the numerically largest of w, x, y, z first.
    """
    M = np.asarray(R, dtype=np.float64)
    if M.shape != (3, 3):
        raise GeometryError(f"rotation_to_quat: expected (3, 3), got {M.shape}")
    tr = M[0, 0] + M[1, 1] + M[2, 2]
    diag = (tr, M[0, 0], M[1, 1], M[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 0.0))
        q = np.array([(M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s, 0.25 * s])
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + M[0, 0] - M[1, 1] - M[2, 2], 0.0))
        q = np.array([0.25 * s, (M[0, 1] + M[1, 0]) / s, (M[0, 2] + M[2, 0]) / s, (M[2, 1] - M[1, 2]) / s])
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 + M[1, 1] - M[0, 0] - M[2, 2], 0.0))
        q = np.array([(M[0, 1] + M[1, 0]) / s, 0.25 * s, (M[1, 2] + M[2, 1]) / s, (M[0, 2] - M[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(max(1.0 + M[2, 2] - M[0, 0] - M[1, 1], 0.0))
        q = np.array([(M[0, 2] + M[2, 0]) / s, (M[1, 2] + M[2, 1]) / s, 0.25 * s, (M[1, 0] - M[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def transform_from_tum(values: ArrayLike) -> F64:
    """``T`` (4, 4) from a TUM pose row ``tx ty tz qx qy qz qw`` (7 values)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.shape != (7,):
        raise GeometryError(f"TUM pose: expected 7 values, got {v.shape[0]}")
    return make_transform(quat_to_rotation(v[3:]), v[:3])


def transform_to_tum(T: ArrayLike) -> F64:
    """TUM pose row ``tx ty tz qx qy qz qw`` (7,) from ``T`` (4, 4)."""
    M = np.asarray(T, dtype=np.float64)
    return np.concatenate([M[:3, 3], rotation_to_quat(M[:3, :3])])


def hat(v: ArrayLike) -> F64:
    """Skew-symmetric matrices (..., 3, 3) of 3-vectors (..., 3): ``hat(a) @ b == cross(a, b)``."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise GeometryError(f"hat: expected 3-vectors (..., 3), got shape {a.shape}")
    out = np.zeros((*a.shape, 3))
    out[..., 0, 1], out[..., 0, 2] = -a[..., 2], a[..., 1]
    out[..., 1, 0], out[..., 1, 2] = a[..., 2], -a[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -a[..., 1], a[..., 0]
    return out


def so3_exp(omega: ArrayLike) -> F64:
    """Rotation (3, 3) from an axis-angle vector (3,) in radians (Rodrigues)."""
    w = np.asarray(omega, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    K = hat(w)
    if theta < 1e-9:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K


def so3_log(R: ArrayLike) -> F64:
    """Axis-angle vector (3,) in radians of a rotation (3, 3); angle in [0, pi]."""
    M = np.asarray(R, dtype=np.float64)
    cos_t = np.clip((np.trace(M) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    if theta < 1e-9:
        return np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]]) / 2.0
    if np.pi - theta < 1e-6:
        # Near pi: axis from the symmetric part.
        B = (M + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        k = int(np.argmax(axis))
        axis = B[k] / axis[k]
        return theta * axis / np.linalg.norm(axis)
    w = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return theta / (2.0 * np.sin(theta)) * w


def se3_exp(xi: ArrayLike) -> F64:
    """``T`` (4, 4) from a twist ``(rho, omega)`` (6,): metres then radians."""
    v = np.asarray(xi, dtype=np.float64).reshape(6)
    rho, omega = v[:3], v[3:]
    theta = float(np.linalg.norm(omega))
    K = hat(omega)
    if theta < 1e-9:
        V = np.eye(3) + 0.5 * K
    else:
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K
    return make_transform(so3_exp(omega), V @ rho)


def se3_log(T: ArrayLike) -> F64:
    """Twist ``(rho, omega)`` (6,) of ``T`` (4, 4); inverse of :func:`se3_exp`."""
    M = np.asarray(T, dtype=np.float64)
    omega = so3_log(M[:3, :3])
    theta = float(np.linalg.norm(omega))
    K = hat(omega)
    if theta < 1e-9:
        V_inv = np.eye(3) - 0.5 * K
    else:
        a = (1 - theta * np.sin(theta) / (2 * (1 - np.cos(theta)))) / theta**2
        V_inv = np.eye(3) - 0.5 * K + a * K @ K
    return np.concatenate([V_inv @ M[:3, 3], omega])


def rotation_angle(R: ArrayLike) -> float:
    """Angle in radians (0..pi) of a rotation matrix (3, 3)."""
    M = np.asarray(R, dtype=np.float64)
    return float(np.arccos(np.clip((np.trace(M) - 1.0) / 2.0, -1.0, 1.0)))


def slerp(q0_xyzw: ArrayLike, q1_xyzw: ArrayLike, s: float) -> F64:
    """Spherical interpolation between unit quaternions at ``s`` in [0, 1]; shortest arc."""
    q0 = np.asarray(q0_xyzw, dtype=np.float64)
    q1 = np.asarray(q1_xyzw, dtype=np.float64)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(d)
    q = (np.sin((1 - s) * th) * q0 + np.sin(s * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


def interpolate_transform(T0: ArrayLike, T1: ArrayLike, s: float) -> F64:
    """Pose between ``T0`` and ``T1`` at fraction ``s``: linear translation, slerp rotation."""
    A = np.asarray(T0, dtype=np.float64)
    B = np.asarray(T1, dtype=np.float64)
    q = slerp(rotation_to_quat(A[:3, :3]), rotation_to_quat(B[:3, :3]), s)
    return make_transform(quat_to_rotation(q), (1 - s) * A[:3, 3] + s * B[:3, 3])


def yaw_rotation(yaw: float) -> F64:
    """Rotation (3, 3) by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_transform(x: float, y: float, yaw: float, z: float = 0.0) -> F64:
    """Planar pose (4, 4) of a ground robot: translation (x, y, z), rotation yaw about +z."""
    return make_transform(yaw_rotation(yaw), [x, y, z])
