"""Registration tracker → model frame and time alignment by cross-correlation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softphantom.errors import UserError
from softphantom.pose import RigidTransform, matrix_from_ypr
from softphantom.tracking import (
    estimate_lag,
    make_track,
    pose_columns,
    register_track,
    registration_from_markers,
    shift_to_common_start,
    track_pose6,
)

RNG = np.random.default_rng(12345)


def random_transform(rng):
    return RigidTransform(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(scale=1.0, size=3))


def push_profile(t, t0=1.0, rise=0.6, hold=1.0, amp=1.0):
    """Smooth push: cosine ramp up, hold, ramp down."""
    up = np.clip((t - t0) / rise, 0, 1)
    down = np.clip((t - t0 - rise - hold) / rise, 0, 1)
    return amp * 0.5 * ((1 - np.cos(np.pi * up)) - (1 - np.cos(np.pi * down)))


def test_registration_from_reference_markers_recovers_transform():
    T_true = random_transform(RNG)  # tracker -> model
    model_pts = RNG.uniform(-0.1, 0.1, size=(5, 3))
    tracker_pts = T_true.inverse().apply(model_pts)
    T = registration_from_markers(tracker_pts, model_pts)
    assert np.max(np.abs(T.R - T_true.R)) < 1e-12 and np.max(np.abs(T.t - T_true.t)) < 1e-12
    # with the tracker's ±0.19 mm: error well under a millimetre / a tenth of a degree
    noisy = tracker_pts + RNG.normal(scale=0.19e-3, size=tracker_pts.shape)
    Tn = registration_from_markers(noisy, model_pts)
    ang = np.degrees(Rotation.from_matrix(Tn.R @ T_true.R.T).magnitude())
    # (the tracker origin is ~1 m away: compare where the phantom is, not at the origin)
    assert np.max(np.linalg.norm(Tn.apply(tracker_pts) - model_pts, axis=1)) < 1e-3
    assert ang < 0.5
    assert 0.03e-3 < Tn.rms_residual < 0.4e-3


def _relative_motion(n):
    t = np.arange(n) / 120.0
    s = push_profile(t, t0=1.0)
    ypr = np.column_stack([0.10 * s, -0.05 * s, 0.02 * s])  # rad
    xyz = np.column_stack([0.001 * s, 0.006 * s, -0.002 * s])  # m
    return t, RigidTransform(matrix_from_ypr(ypr), xyz), ypr, xyz


def _track_from(T_WB, t, valid=None):
    q = Rotation.from_matrix(T_WB.R).as_quat()
    pos = T_WB.t.copy()
    if valid is not None:
        pos[~valid] = np.nan
    return make_track(t, pos, q, clock="take_time", source="synthetic", name="bip")


def test_register_with_markers_transform_recovers_relative_motion():
    t, T_rel, ypr, xyz = _relative_motion(480)
    T_MW = random_transform(RNG)  # tracker -> model (known from reference markers)
    # body pivot off the bulb centre, body axes not the model's
    T_MB0 = RigidTransform(Rotation.random(random_state=3).as_matrix(), np.array([0.01, -0.03, 0.02]))
    T_WB = T_MW.inverse().compose(T_rel.compose(T_MB0))
    valid = np.ones(len(t), bool)
    valid[200] = False
    reg = register_track(_track_from(T_WB, t, valid), tracker_to_model=T_MW, rest_window_s=(0.0, 0.5))
    p6 = track_pose6(reg)
    assert reg.meta["registration"] == "given tracker-to-model transform"
    assert np.isnan(p6.xyz[200]).all() and not reg.valid[200]
    assert np.nanmax(np.abs(p6.xyz - xyz)) < 1e-12
    assert np.nanmax(np.abs(p6.ypr - ypr)) < 1e-12


def test_register_by_rest_window_recovers_relative_motion():
    t, T_rel, ypr, xyz = _relative_motion(480)
    T_WM = random_transform(RNG)  # unknown to the registration
    T_WB = T_WM.compose(T_rel)  # body frame = model frame at rest
    reg = register_track(_track_from(T_WB, t))  # default window: first 0.5 s (at rest)
    assert reg.meta["registration"] == "rest window" and reg.meta["rest_samples"] == 61
    p6 = track_pose6(reg)
    assert np.max(np.abs(p6.xyz - xyz)) < 1e-12 and np.max(np.abs(p6.ypr - ypr)) < 1e-12
    cols = pose_columns(reg)
    assert list(cols) == ["t_s", "x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg"]
    np.testing.assert_allclose(cols["y_mm"], xyz[:, 1] * 1e3, atol=1e-9)
    np.testing.assert_allclose(cols["yaw_deg"], np.degrees(ypr[:, 0]), atol=1e-9)


def test_rest_window_with_noise_and_errors():
    t, T_rel, ypr, xyz = _relative_motion(480)
    T_WB = random_transform(RNG).compose(T_rel)
    tr = _track_from(T_WB, t)
    noisy = make_track(tr.t, tr.position + RNG.normal(scale=0.19e-3, size=tr.position.shape), tr.quat_xyzw,
                       clock=tr.clock, source=tr.source, name=tr.name)
    p6 = track_pose6(register_track(noisy, rest_window_s=(0.0, 0.9)))
    err = np.abs(p6.xyz - xyz)
    assert np.sqrt(np.mean(err**2)) < 0.3e-3  # of the order of the tracker noise
    with pytest.raises(UserError, match="no valid sample .* in the rest window 10.000–11.000 s"):
        register_track(tr, rest_window_s=(10.0, 11.0))


@pytest.mark.parametrize("lag_ms", [100.0, 35.0, -60.0, 0.0])
def test_lag_recovered_within_5ms(lag_ms):
    rng = np.random.default_rng(int(abs(lag_ms)) + 1)
    # truth: 120 Hz tracker, ±0.19 mm noise; two pushes of different size along y and x
    t_truth = np.arange(0, 8, 1 / 120)

    def motion(t):
        y = push_profile(t, 1.0, 0.5, 0.8, 6.0) + push_profile(t, 4.2, 0.4, 0.5, 3.0)
        x = push_profile(t, 1.0, 0.5, 0.8, 1.2) - push_profile(t, 4.2, 0.4, 0.5, 0.8)
        return np.column_stack([x, y])

    truth = motion(t_truth) + rng.normal(scale=0.19, size=(len(t_truth), 2))
    # estimate: ~77 Hz with jitter, later by lag, with its own error (gain, noise)
    t_est = np.cumsum(rng.uniform(0.9, 1.1, 700) / 77.0)
    t_est = t_est[t_est < 8.0]
    est = 1.08 * motion(t_est - lag_ms / 1e3) + rng.normal(scale=0.1, size=(len(t_est), 2))
    r = estimate_lag(t_truth, truth, t_est, est, max_lag_s=0.5)
    assert abs(r.lag_ms - lag_ms) < 5.0, r
    assert r.peak_corr > 0.95 and not r.at_edge
    # one channel alone too
    r1 = estimate_lag(t_truth, truth[:, 1], t_est, est[:, 1], max_lag_s=0.5)
    assert abs(r1.lag_ms - lag_ms) < 5.0


def test_lag_sign_convention_and_guards():
    t = np.linspace(0, 5, 1001)
    f = push_profile(t, 1.5, 0.5, 0.5)
    later = push_profile(t - 0.2, 1.5, 0.5, 0.5)
    assert estimate_lag(t, f, t, later).lag_ms == pytest.approx(200.0, abs=1.0)
    assert estimate_lag(t, later, t, f).lag_ms == pytest.approx(-200.0, abs=1.0)
    with pytest.raises(ValueError, match="same clock"):
        estimate_lag(t, f, t + 100.0, f)
    with pytest.raises(ValueError, match="no channel varies"):
        estimate_lag(t, np.ones_like(t), t, f)
    a, b, shifted = shift_to_common_start(t + 1.7e9, t)
    assert shifted and a[0] == 0.0 and b[0] == 0.0
