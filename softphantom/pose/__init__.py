"""Pose library (a leaf: imports nothing from the other stages).

Rigid fit of marker points, the project's Euler convention ``R = Rz(yaw)·Rx(pitch)·Ry(roll)``
(scipy's intrinsic ``'ZXY'``), quaternions (x, y, z, w), and :class:`Pose6`.
"""

from softphantom.pose.rigid import (
    DegenerateMarkersError,
    Pose6,
    RigidTransform,
    pose_of_markers,
    rigid_fit,
)
from softphantom.pose.rotations import (
    matrix_from_quat,
    matrix_from_ypr,
    mean_quat,
    quat_from_matrix,
    quat_from_ypr,
    rot_x,
    rot_y,
    rot_z,
    ypr_from_matrix,
    ypr_from_quat,
)

__all__ = [
    "DegenerateMarkersError",
    "Pose6",
    "RigidTransform",
    "matrix_from_quat",
    "matrix_from_ypr",
    "mean_quat",
    "pose_of_markers",
    "quat_from_matrix",
    "quat_from_ypr",
    "rigid_fit",
    "rot_x",
    "rot_y",
    "rot_z",
    "ypr_from_matrix",
    "ypr_from_quat",
]
