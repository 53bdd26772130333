"""Rigid fit of marker points (Kabsch) and the 6-DoF pose of the marker rigid body.

Pose convention (docs/evaluation.md): the pose relative to rest is the rigid motion
``x = R·x_rest + t`` in the model frame that best maps the rest markers onto the current ones.
Its translation ``t`` is the displacement of the model origin (the bulb centre at rest), so a pure
rotation about the bulb centre has zero translation; the angles are those of ``R`` in the
project's Euler convention (``R = Rz(yaw)·Rx(pitch)·Ry(roll)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError
from softphantom.pose.rotations import matrix_from_ypr, ypr_from_matrix

#: Markers whose spread (2nd singular value of the centred points) is below this fraction of the
#: largest one are treated as collinear: the rotation about their line is not observable.
DEGENERACY_RATIO = 1e-6


class DegenerateMarkersError(UserError):
    """Marker points that do not determine a rotation (fewer than 3, coincident or collinear)."""


@dataclass(frozen=True)
class RigidTransform:
    """``x' = R·x + t``; ``R`` (..., 3, 3), ``t`` (..., 3) m, ``rms_residual`` (...) m."""

    R: np.ndarray
    t: np.ndarray
    rms_residual: np.ndarray | float = 0.0

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Transform points ``(..., k, 3)`` (broadcast over the stack of transforms)."""
        return np.einsum("...ij,...kj->...ki", self.R, np.asarray(x, dtype=float)) + self.t[..., None, :]

    def inverse(self) -> "RigidTransform":
        """The inverse transform ``x = Rᵀ·(x' − t)``."""
        Rt = np.swapaxes(self.R, -1, -2)
        return RigidTransform(Rt, -np.einsum("...ij,...j->...i", Rt, self.t), self.rms_residual)

    def compose(self, other: "RigidTransform") -> "RigidTransform":
        """``self ∘ other``: apply ``other`` first, then ``self``."""
        return RigidTransform(
            self.R @ other.R, np.einsum("...ij,...j->...i", self.R, other.t) + self.t, self.rms_residual
        )


def rigid_fit(rest_points: np.ndarray, points: np.ndarray, weights: np.ndarray | None = None) -> RigidTransform:
    """Least-squares rigid transform (no scale) with ``points ≈ R·rest_points + t``.

    ``rest_points`` (k, 3); ``points`` (k, 3) or a stack ``(n, k, 3)`` (one fit per frame);
    ``weights`` (k,) ≥ 0. Kabsch/Umeyama by SVD, with the reflection guard (det R = +1).
    Raises :class:`DegenerateMarkersError` for < 3 points or coincident/collinear rest points.

    >>> rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> f = rigid_fit(rest, rest + [0.1, 0.2, 0.3])
    >>> np.allclose(f.R, np.eye(3)), np.round(f.t, 12) + 0.0
    (True, array([0.1, 0.2, 0.3]))
    """
    P = np.asarray(rest_points, dtype=float)
    Q = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise DegenerateMarkersError(f"rest points must be (k, 3), got shape {P.shape}")
    if Q.shape[-2:] != P.shape:
        raise DegenerateMarkersError(f"points {Q.shape} do not match rest points {P.shape}")
    k = P.shape[0]
    w = np.ones(k) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (k,) or np.any(w < 0) or np.count_nonzero(w) < 3:
        raise DegenerateMarkersError(f"need >= 3 markers with positive weight, got {np.count_nonzero(w)}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(Q))):
        raise DegenerateMarkersError("marker coordinates are not all finite (lost markers?)")
    w = w / w.sum()
    cp = w @ P
    cq = np.einsum("k,...kj->...j", w, Q)
    P0 = P - cp
    Q0 = Q - cq[..., None, :]
    sv = np.linalg.svd(P0 * np.sqrt(w)[:, None], compute_uv=False)
    if sv[0] <= 0 or sv[1] < DEGENERACY_RATIO * sv[0]:
        raise DegenerateMarkersError(
            f"rest markers are coincident or collinear (spread singular values {sv[0]:.3g}, {sv[1]:.3g}):"
            " a rotation about their line is not observable"
        )
    H = np.einsum("k,ki,...kj->...ij", w, P0, Q0)  # Σ w p q^T
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = V @ D @ np.swapaxes(U, -1, -2)
    t = cq - np.einsum("...ij,j->...i", R, cp)
    res = Q - (np.einsum("...ij,kj->...ki", R, P) + t[..., None, :])
    rms = np.sqrt(np.einsum("k,...k->...", w, np.sum(res * res, axis=-1)))
    return RigidTransform(R, t, rms)


@dataclass(frozen=True)
class Pose6:
    """6-DoF pose relative to rest: ``xyz`` (..., 3) m, ``ypr`` (..., 3) rad (yaw, pitch, roll).

    >>> p = Pose6(np.array([0.001, 0.002, 0.0]), np.radians([10.0, 0.0, 0.0]))
    >>> np.round(p.to_mm_deg(), 9) + 0.0
    array([ 1.,  2.,  0., 10.,  0.,  0.])
    """

    xyz: np.ndarray
    ypr: np.ndarray

    #: Column names of :meth:`to_mm_deg`, as in the estimate and truth files.
    COLUMNS = ("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg")

    def to_mm_deg(self) -> np.ndarray:
        """``(..., 6)`` array: x, y, z in mm, then yaw, pitch, roll in degrees."""
        return np.concatenate([np.asarray(self.xyz) * 1e3, np.degrees(self.ypr)], axis=-1)

    @classmethod
    def from_mm_deg(cls, v: np.ndarray) -> "Pose6":
        """Inverse of :meth:`to_mm_deg`."""
        v = np.asarray(v, dtype=float)
        return cls(v[..., :3] * 1e-3, np.radians(v[..., 3:6]))

    @classmethod
    def from_transform(cls, T: RigidTransform) -> "Pose6":
        """Pose of a rigid transform (translation, Euler angles of the rotation)."""
        return cls(np.asarray(T.t, dtype=float), ypr_from_matrix(T.R))

    def matrix(self) -> np.ndarray:
        """The rotation matrices ``R = Rz(yaw)·Rx(pitch)·Ry(roll)``."""
        return matrix_from_ypr(self.ypr)

    def transform(self) -> RigidTransform:
        """As a :class:`RigidTransform`."""
        return RigidTransform(self.matrix(), np.asarray(self.xyz, dtype=float))


def pose_of_markers(rest_markers: np.ndarray, markers: np.ndarray, weights: np.ndarray | None = None) -> Pose6:
    """6-DoF pose of the marker rigid body relative to rest (model frame, origin at the bulb
    centre at rest): the rigid fit ``markers ≈ R·rest_markers + t``; ``markers`` may be a stack.

    A pure rotation about the origin gives zero translation:

    >>> rest = np.array([[0.03, 0, 0], [0, 0.025, 0], [0, 0, 0.03], [-0.03, 0, 0.01]])
    >>> p = pose_of_markers(rest, rest @ matrix_from_ypr([0.2, 0.0, 0.0]).T)
    >>> (np.round(p.to_mm_deg(), 6) + 0.0).tolist()
    [0.0, 0.0, 0.0, 11.459156, 0.0, 0.0]
    """
    return Pose6.from_transform(rigid_fit(rest_markers, markers, weights))
