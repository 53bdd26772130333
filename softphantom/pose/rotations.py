"""Rotations in the one Euler convention of the project, vectorized over stacks.

Convention (docs/architecture.md): ``R = Rz(yaw) · Rx(pitch) · Ry(roll)`` — intrinsic z, then x′,
then y″; right-handed; radians inside. It is scipy's intrinsic ``'ZXY'`` sequence
(``Rotation.from_euler('ZXY', [yaw, pitch, roll])``), which the tests check.

Quaternions are scalar-last ``(x, y, z, w)`` like ROS and Motive; returned with ``w >= 0``.
"""

from __future__ import annotations

import numpy as np

#: |cos(pitch)| below this is treated as gimbal lock (pitch = ±90°): roll is set to 0 then.
GIMBAL_EPS = 1e-9


def rot_x(a: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about x by ``a`` rad, shape ``a.shape + (3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(a.shape + (3, 3))


def rot_y(a: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about y by ``a`` rad."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(a.shape + (3, 3))


def rot_z(a: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about z by ``a`` rad."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(a.shape + (3, 3))


def matrix_from_ypr(ypr: np.ndarray) -> np.ndarray:
    """``R = Rz(yaw)·Rx(pitch)·Ry(roll)`` from ``(..., 3)`` angles in rad (yaw, pitch, roll).

    >>> R = matrix_from_ypr([np.pi / 2, 0.0, 0.0])   # yaw 90°: x axis -> y axis
    >>> np.round(R @ [1.0, 0.0, 0.0], 12) + 0.0
    array([0., 1., 0.])
    """
    ypr = np.asarray(ypr, dtype=float)
    if ypr.shape[-1] != 3:
        raise ValueError(f"ypr must have a last axis of 3, got shape {ypr.shape}")
    return rot_z(ypr[..., 0]) @ rot_x(ypr[..., 1]) @ rot_y(ypr[..., 2])


def ypr_from_matrix(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) rad of ``(..., 3, 3)`` rotation matrices; pitch in [−π/2, π/2].

    Expanding the product: ``R[2,1] = sin(pitch)``, ``R[0,1] = −sin(yaw)cos(pitch)``,
    ``R[1,1] = cos(yaw)cos(pitch)``, ``R[2,0] = −cos(pitch)sin(roll)``, ``R[2,2] =
    cos(pitch)cos(roll)``. At gimbal lock (cos(pitch) ≈ 0) yaw and roll are not separable: roll
    is set to 0 and yaw carries the whole rotation about z — deterministic.

    >>> ypr = np.array([0.3, -0.2, 0.1])
    >>> np.allclose(ypr_from_matrix(matrix_from_ypr(ypr)), ypr)
    True
    """
    R = np.asarray(R, dtype=float)
    cp = np.hypot(R[..., 2, 0], R[..., 2, 2])
    pitch = np.arctan2(R[..., 2, 1], cp)
    locked = cp < GIMBAL_EPS
    yaw = np.where(locked, np.arctan2(R[..., 1, 0], R[..., 0, 0]), np.arctan2(-R[..., 0, 1], R[..., 1, 1]))
    roll = np.where(locked, 0.0, np.arctan2(-R[..., 2, 0], R[..., 2, 2]))
    return np.stack([yaw, pitch, roll], axis=-1)


def matrix_from_quat(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices from ``(..., 4)`` quaternions (x, y, z, w); normalized first.

    >>> np.allclose(matrix_from_quat([0, 0, 0, 1]), np.eye(3))
    True
    """
    q = np.asarray(q_xyzw, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(n)):
        raise ValueError("quaternion of zero or non-finite norm")
    x, y, z, w = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w), ``w >= 0``, of ``(..., 3, 3)`` rotation matrices.

    Shepperd's method: take the largest of the four squared components to divide by, so
    that no branch loses precision.

    >>> np.round(quat_from_matrix(rot_z(np.pi / 2)), 12) + 0.0
    array([0.        , 0.        , 0.70710678, 0.70710678])
    """
    R = np.asarray(R, dtype=float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # 4·(w², x², y², z²) up to the common trace terms
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    q = np.stack(
        [
            np.stack([d21 / s, d02 / s, d10 / s, s / 4], -1),  # w largest
            np.stack([s / 4, s10 / s, s02 / s, d21 / s], -1),  # x largest
            np.stack([s10 / s, s / 4, s21 / s, d02 / s], -1),  # y largest
            np.stack([s02 / s, s21 / s, s / 4, d10 / s], -1),  # z largest
        ],
        -2,
    )
    q = np.take_along_axis(q, k[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def ypr_from_quat(q_xyzw: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) rad of ``(..., 4)`` quaternions (x, y, z, w)."""
    return ypr_from_matrix(matrix_from_quat(q_xyzw))


def quat_from_ypr(ypr: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) of ``(..., 3)`` angles (yaw, pitch, roll) in rad."""
    return quat_from_matrix(matrix_from_ypr(ypr))


def mean_quat(q_xyzw: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Average rotation of ``(n, 4)`` quaternions (Markley et al. 2007: the principal
    eigenvector of ``Σ w q qᵀ``; insensitive to the sign of each q).

    >>> q = quat_from_ypr(np.array([[0.1, 0, 0], [0.3, 0, 0]]))
    >>> np.round(ypr_from_quat(mean_quat(q)), 12) + 0.0
    array([0.2, 0. , 0. ])
    """
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w = np.ones(len(q)) if weights is None else np.asarray(weights, dtype=float)
    M = np.einsum("n,ni,nj->ij", w, q, q)
    _, vecs = np.linalg.eigh(M)
    m = vecs[:, -1]
    return m if m[3] >= 0 else -m
