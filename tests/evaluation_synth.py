"""Synthetic estimate/truth runs for the evaluation tests (not a test module itself)."""

from __future__ import annotations

import numpy as np

from softphantom.evaluation import write_table
from softphantom.pose import Pose6


def push(t, t0, rise, hold, amp):
    up = np.clip((t - t0) / rise, 0, 1)
    down = np.clip((t - t0 - rise - hold) / rise, 0, 1)
    return amp * 0.5 * ((1 - np.cos(np.pi * up)) - (1 - np.cos(np.pi * down)))


PEAKS = np.array([1.5, 6.0, -1.2, 3.0, -5.0, 0.8])  # x, y, z mm; yaw, pitch, roll deg (push 1)


def motion(t):
    s1 = push(t, 1.0, 0.6, 1.0, 1.0)
    s2 = push(t, 4.0, 0.5, 0.6, 1.0)
    v = np.outer(s1, PEAKS) + np.outer(s2, PEAKS * [-0.5, 0.6, 1.0, -1.0, 0.5, 0.3])
    force = np.outer(s1, [0.3, 3.0, -0.2]) + np.outer(s2, [-0.2, 1.8, 0.1])
    return v, force


def write_run(tmpdir, lag_ms=100.0, seed=0, gain=1.05, noise_mm=0.19, est_noise=0.05, est_start_s=0.25,
              truth_meta=None, estimate_meta=None):
    """Truth at 120 Hz with tracker noise (and 0.05° on the angles); estimate at ~77 Hz with jitter,
    later by ``lag_ms``, scaled by ``gain``, starting ``est_start_s`` after the truth (same clock;
    the files' metadata say so only if ``truth_meta``/``estimate_meta`` add a ``clock``)."""
    rng = np.random.default_rng(seed)
    t_truth = np.arange(0.0, 7.0, 1 / 120)
    v, f = motion(t_truth)
    v = v + rng.normal(scale=[noise_mm] * 3 + [0.25 * noise_mm] * 3, size=v.shape)
    truth = {"t_s": t_truth}
    for k, name in enumerate(Pose6.COLUMNS):
        truth[name] = v[:, k]
    for k, a in enumerate("xyz"):
        truth[f"force_{a}_N"] = f[:, k]
    truth["seed_1_dx_mm"], truth["seed_1_dy_mm"], truth["seed_1_dz_mm"] = v[:, 0] * 0.8, v[:, 1] * 0.9, v[:, 2]
    t_est = np.cumsum(rng.uniform(0.9, 1.1, 560) / 77.0)
    t_est = t_est[t_est < 7.0 - est_start_s] + est_start_s
    ve, fe = motion(t_est - lag_ms / 1e3)
    ve = gain * ve + rng.normal(scale=est_noise, size=ve.shape)
    est = {"t_s": t_est}
    for k, a in enumerate("xyz"):
        est[f"force_{a}_N"] = gain * fe[:, k]
    est["p_urethra_kPa"] = np.zeros(len(t_est))
    for k, name in enumerate(Pose6.COLUMNS):
        est[name] = ve[:, k]
    est["seed_1_dx_mm"], est["seed_1_dy_mm"], est["seed_1_dz_mm"] = ve[:, 0] * 0.8, ve[:, 1] * 0.9, ve[:, 2]
    est["qp_status"] = np.array(["solved"] * len(t_est))
    pt = write_table(tmpdir / "truth.csv", {"softphantom": "0.1.0", "scenario": "synthetic push", **(truth_meta or {})},
                     truth)
    pe = write_table(tmpdir / "estimate.csv", {"softphantom": "0.1.0", "model": "synthetic", **(estimate_meta or {})},
                     est)
    return pe, pt


def write_snapshot(path, with_displacement=True):
    """A small ellipsoid tet mesh (Delaunay of a point cloud), pushed along +y near y < 0."""
    import meshio
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(1)
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = np.vstack([u * [0.032, 0.025, 0.030], rng.uniform(-0.5, 0.5, (60, 3)) * [0.032, 0.025, 0.030]])
    tets = Delaunay(pts).simplices
    disp = np.zeros_like(pts)
    disp[:, 1] = 0.006 * np.exp(-((pts[:, 1] + 0.025) / 0.02) ** 2)
    point_data = {"displacement_mm": disp * 1e3} if with_displacement else {}
    meshio.write(path, meshio.Mesh(pts + disp, [("tetra", tets)], point_data=point_data))
    return path


def write_motive_truth(path, seed=0, noise_mm=0.0, clock_offset_s=0.0):
    """The synthetic motion as a Motive CSV (millimetres, quaternion) of body 'bip', seen from a
    tracker frame rotated and offset from the model frame; the body frame = model frame at rest.
    The take's clock runs ``clock_offset_s`` ahead of the run's (take time = run time + offset)."""
    from scipy.spatial.transform import Rotation

    from softphantom.pose import RigidTransform

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 7.0, 1 / 120)
    v, _ = motion(t)
    T_rel = Pose6.from_mm_deg(v).transform()
    T_WM = RigidTransform(Rotation.from_euler("xyz", [90, 10, -30], degrees=True).as_matrix(), np.array([0.4, 1.2, -0.3]))
    T_WB = T_WM.compose(T_rel)
    pos_mm = T_WB.t * 1e3 + rng.normal(scale=noise_mm, size=T_WB.t.shape)
    q = Rotation.from_matrix(T_WB.R).as_quat()
    lines = [
        "Format Version,1.23,Take Name,synthetic,Capture Frame Rate,120.000000,Export Frame Rate,120.000000,"
        "Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global",
        "",
        ",Type," + ",".join(["Rigid Body"] * 7),
        ",Name," + ",".join(["bip"] * 7),
        ",," + ",".join(["Rotation"] * 4 + ["Position"] * 3),
        "Frame,Time (Seconds),X,Y,Z,W,X,Y,Z",
    ]
    for i in range(len(t)):
        cells = [str(i), f"{t[i] + clock_offset_s:.6f}"] + [f"{x:.9f}" for x in q[i]] + [f"{x:.6f}" for x in pos_mm[i]]
        if i == 300:  # a lost frame
            cells[2:] = [""] * 7
        lines.append(",".join(cells))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path
