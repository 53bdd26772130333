"""Pose library: Euler convention vs scipy, quaternions, Kabsch rigid fit, Pose6."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softphantom.errors import UserError
from softphantom.pose import (
    DegenerateMarkersError,
    Pose6,
    RigidTransform,
    matrix_from_quat,
    matrix_from_ypr,
    mean_quat,
    pose_of_markers,
    quat_from_matrix,
    quat_from_ypr,
    rigid_fit,
    ypr_from_matrix,
    ypr_from_quat,
)

RNG = np.random.default_rng(20240607)


def random_ypr(n, rng=RNG):
    # pitch kept off ±90° so the angles are unique
    return np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-np.pi, np.pi, n)])


def test_convention_is_scipy_intrinsic_ZXY():
    ypr = random_ypr(500)
    R = matrix_from_ypr(ypr)
    ref = Rotation.from_euler("ZXY", ypr).as_matrix()
    assert np.max(np.abs(R - ref)) < 1e-13
    # and not the extrinsic one (a mix-up that would pass with one angle only)
    assert np.max(np.abs(R - Rotation.from_euler("zxy", ypr).as_matrix())) > 0.1


def test_single_axis_meanings_right_handed():
    a = 0.3
    # yaw about z: x axis turns towards +y
    np.testing.assert_allclose(matrix_from_ypr([a, 0, 0]) @ [1, 0, 0], [np.cos(a), np.sin(a), 0], atol=1e-15)
    # pitch about x: y axis turns towards +z
    np.testing.assert_allclose(matrix_from_ypr([0, a, 0]) @ [0, 1, 0], [0, np.cos(a), np.sin(a)], atol=1e-15)
    # roll about y: z axis turns towards +x
    np.testing.assert_allclose(matrix_from_ypr([0, 0, a]) @ [0, 0, 1], [np.sin(a), 0, np.cos(a)], atol=1e-15)


def test_ypr_roundtrip_and_vs_scipy():
    ypr = random_ypr(1000)
    R = matrix_from_ypr(ypr)
    back = ypr_from_matrix(R)
    assert np.max(np.abs(back - ypr)) < 1e-12
    ref = Rotation.from_matrix(R).as_euler("ZXY")
    assert np.max(np.abs(back - ref)) < 1e-9
    # stacks of any leading shape
    assert ypr_from_matrix(R.reshape(10, 100, 3, 3)).shape == (10, 100, 3)


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_gimbal_lock_is_deterministic(pitch):
    R = matrix_from_ypr([0.4, pitch, 0.3])
    ypr = ypr_from_matrix(R)
    assert ypr[2] == 0.0  # roll set to zero
    assert abs(ypr[1] - pitch) < 1e-7
    np.testing.assert_allclose(matrix_from_ypr(ypr), R, atol=1e-12)  # same rotation


def test_quaternions_vs_scipy():
    q = RNG.normal(size=(1000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = matrix_from_quat(q)
    assert np.max(np.abs(R - Rotation.from_quat(q).as_matrix())) < 1e-13
    back = quat_from_matrix(R)
    assert np.all(back[:, 3] >= 0)
    same = np.where(q[:, 3:] < 0, -q, q)
    assert np.max(np.abs(back - same)) < 1e-12
    # near-180° rotations (w ≈ 0) use another branch
    q180 = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.6, 0.8, 0, 1e-9]], float)
    np.testing.assert_allclose(matrix_from_quat(quat_from_matrix(matrix_from_quat(q180))), matrix_from_quat(q180), atol=1e-12)
    ypr = random_ypr(200)
    np.testing.assert_allclose(ypr_from_quat(quat_from_ypr(ypr)), ypr, atol=1e-12)
    np.testing.assert_allclose(
        np.abs(np.sum(quat_from_ypr(ypr) * Rotation.from_euler("ZXY", ypr).as_quat(), axis=1)), 1.0, atol=1e-12
    )


def test_mean_quat_vs_scipy():
    base = Rotation.from_euler("ZXY", [0.3, -0.2, 0.1])
    q = (base * Rotation.from_rotvec(RNG.normal(scale=0.01, size=(200, 3)))).as_quat()
    q[::2] *= -1  # the sign of a quaternion must not matter
    m = mean_quat(q)
    ref = Rotation.from_quat(q).mean().as_quat()
    assert abs(abs(m @ ref) - 1.0) < 1e-12


def test_rigid_fit_exact_for_rigid_motion_stack():
    rest = RNG.normal(scale=0.03, size=(6, 3))
    ypr = random_ypr(50)
    t = RNG.normal(scale=0.01, size=(50, 3))
    R = matrix_from_ypr(ypr)
    pts = np.einsum("nij,kj->nki", R, rest) + t[:, None, :]
    fit = rigid_fit(rest, pts)
    assert np.max(np.abs(fit.R - R)) < 1e-12
    assert np.max(np.abs(fit.t - t)) < 1e-12
    assert np.max(fit.rms_residual) < 1e-12
    pose = pose_of_markers(rest, pts)
    assert np.max(np.abs(pose.xyz - t)) < 1e-12
    assert np.max(np.abs(pose.ypr - ypr)) < 1e-12


def test_pure_rotation_about_bulb_centre_has_zero_translation():
    rest = np.array([[0.032, 0, 0], [0, 0.025, 0.01], [0, 0, 0.03], [-0.02, -0.02, 0.0]])
    R = matrix_from_ypr([0.1, 0.05, -0.08])
    pose = pose_of_markers(rest, rest @ R.T)
    assert np.max(np.abs(pose.xyz)) < 1e-14
    # the same rotation about a point off the centre translates the origin
    c = np.array([0.0, -0.03, 0.0])
    pose2 = pose_of_markers(rest, (rest - c) @ R.T + c)
    np.testing.assert_allclose(pose2.xyz, c - R @ c, atol=1e-14)


def test_reflection_guard():
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    mirrored = rest * [1, 1, -1]  # the best orthogonal map is a reflection
    fit = rigid_fit(rest, mirrored)
    assert np.linalg.det(fit.R) > 0.999
    assert fit.rms_residual > 0.1


def test_small_noise_small_error():
    rng = np.random.default_rng(7)
    rest = rng.normal(scale=0.03, size=(5, 3))
    R = matrix_from_ypr([0.2, -0.1, 0.05])
    t = np.array([0.002, 0.006, -0.001])
    sigma = 0.19e-3
    noisy = rest @ R.T + t + rng.normal(scale=sigma, size=(200, 5, 3))
    pose = pose_of_markers(rest, noisy)
    err_mm = np.abs(pose.xyz - t) * 1e3
    err_deg = np.degrees(np.abs(pose.ypr - ypr_from_matrix(R)))
    assert err_mm.max() < 1.0 and np.sqrt(np.mean(err_mm**2)) < 0.3
    assert err_deg.max() < 2.0
    # the rms residual estimates the noise: sqrt(3 (k-2)/k) σ for k markers (6 DoF taken by the fit)
    expected = sigma * np.sqrt(3 * (5 - 2) / 5)
    assert abs(np.mean(rigid_fit(rest, noisy).rms_residual) - expected) < 0.15 * expected


def test_weights_ignore_a_wild_marker():
    rest = RNG.normal(scale=0.03, size=(5, 3))
    R = matrix_from_ypr([0.3, 0.1, 0.0])
    pts = rest @ R.T + 0.01
    pts[4] += 0.05  # a mislabelled marker
    fit = rigid_fit(rest, pts, weights=[1, 1, 1, 1, 0])
    assert np.max(np.abs(fit.R - R)) < 1e-12


@pytest.mark.parametrize(
    "rest",
    [
        np.zeros((4, 3)),  # coincident
        np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float),  # collinear
        np.array([[0, 0, 0], [1, 0, 0]], float),  # too few
    ],
)
def test_degenerate_markers_raise_typed_error(rest):
    with pytest.raises(DegenerateMarkersError) as ei:
        rigid_fit(rest, rest)
    assert isinstance(ei.value, UserError)


def test_nan_markers_raise():
    rest = RNG.normal(size=(4, 3))
    pts = rest.copy()
    pts[1, 0] = np.nan
    with pytest.raises(DegenerateMarkersError, match="finite"):
        rigid_fit(rest, pts)


def test_pose6_units_and_transform_roundtrip():
    v = np.array([[1.5, -2.0, 0.25, 10.0, -5.0, 3.0], [0, 0, 0, 0, 0, 0]])
    p = Pose6.from_mm_deg(v)
    np.testing.assert_allclose(p.xyz[0], [1.5e-3, -2e-3, 0.25e-3])
    np.testing.assert_allclose(p.to_mm_deg(), v, atol=1e-12)
    T = p.transform()
    assert isinstance(T, RigidTransform)
    np.testing.assert_allclose(Pose6.from_transform(T).to_mm_deg(), v, atol=1e-12)
    x = RNG.normal(size=(3, 3))
    np.testing.assert_allclose(T.inverse().apply(T.apply(x)), np.broadcast_to(x, (2, 3, 3)), atol=1e-14)
    np.testing.assert_allclose(T.compose(T.inverse()).R, np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-14)
    assert Pose6.COLUMNS == ("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg")
