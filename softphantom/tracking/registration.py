"""Registration of a tracked rigid body into the model frame, and its 6-DoF motion relative to rest.

Two ways to know the tracker → model transform ``T_MW`` (``x_model = A·x_tracker + b``):

(a) reference markers fixed on the frame, with known model coordinates and measured tracker
    coordinates: :func:`registration_from_markers` (a rigid fit);
(b) a rest-pose calibration window: the body's mean pose during rest *is* the model's rest pose
    (the rigid body's pivot defined at the bulb centre and its axes along the model's x, y, z):
    ``T_MW = T_WB0⁻¹``.

Either way the motion relative to rest in the model frame is ``T_MB(t) · T_MB(rest)⁻¹``: with
``x = R·x_rest + t`` its translation is the displacement of the model origin (the bulb centre at
rest), the convention of :func:`softphantom.pose.pose_of_markers`.
"""

from __future__ import annotations

import numpy as np

from softphantom.errors import UserError
from softphantom.pose import Pose6, RigidTransform, matrix_from_quat, mean_quat, quat_from_matrix, rigid_fit, ypr_from_matrix
from softphantom.tracking.track import PoseTrack

#: Default rest window: the first half second of valid samples.
DEFAULT_REST_WINDOW_S = 0.5


def registration_from_markers(tracker_points: np.ndarray, model_points: np.ndarray, weights=None) -> RigidTransform:
    """Tracker → model transform from reference markers: ``model ≈ R·tracker + t`` (m).

    >>> rng = np.random.default_rng(0); m = rng.normal(size=(4, 3))
    >>> T = registration_from_markers(m + [1.0, 2.0, 3.0], m)
    >>> np.round(T.t, 12) + 0.0
    array([-1., -2., -3.])
    """
    return rigid_fit(np.asarray(tracker_points, float), np.asarray(model_points, float), weights)


def rest_window(track: PoseTrack, window_s: tuple[float, float] | None = None) -> np.ndarray:
    """Boolean mask of the valid samples in the rest window (default: the first 0.5 s of valid
    samples; ``window_s`` is ``(start, end)`` s on the track's clock)."""
    tv = track.t[track.valid]
    if len(tv) == 0:
        raise UserError(f"{track.source}: body {track.name!r} has no valid sample")
    lo, hi = (tv[0], tv[0] + DEFAULT_REST_WINDOW_S) if window_s is None else window_s
    mask = track.valid & (track.t >= lo) & (track.t <= hi)
    if not mask.any():
        raise UserError(
            f"{track.source}: no valid sample of {track.name!r} in the rest window {lo:.3f}–{hi:.3f} s"
            f" (the track spans {tv[0]:.3f}–{tv[-1]:.3f} s on its {track.clock} clock)"
        )
    return mask


def rest_pose(track: PoseTrack, window_s: tuple[float, float] | None = None) -> RigidTransform:
    """The body's mean pose in the tracker frame during the rest window (mean position, Markley
    mean rotation); ``rms_residual`` is the RMS distance of the positions from their mean (m),
    a check that the body was at rest."""
    m = rest_window(track, window_s)
    p = track.position[m]
    q = mean_quat(track.quat_xyzw[m])
    spread = float(np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, axis=1))))
    return RigidTransform(matrix_from_quat(q), p.mean(0), spread)


def register_track(
    track: PoseTrack,
    tracker_to_model: RigidTransform | None = None,
    rest_window_s: tuple[float, float] | None = None,
    rest: RigidTransform | None = None,
) -> PoseTrack:
    """The body's motion relative to rest, in the model frame, as a new :class:`PoseTrack`.

    ``position`` is then the translation ``t`` and ``quat_xyzw`` the rotation ``R`` of
    ``x = R·x_rest + t`` (model frame). Without ``tracker_to_model`` the rest pose defines the
    model frame (way (b) above). Clock and validity are kept. ``rest`` gives the rest pose (from an
    earlier part of the same take, e.g. when a live recording registers as it goes).
    """
    given_rest = rest is not None
    rest = rest if given_rest else rest_pose(track, rest_window_s)
    given = tracker_to_model
    if tracker_to_model is None:
        tracker_to_model = rest.inverse()
    A, b = np.asarray(tracker_to_model.R, float), np.asarray(tracker_to_model.t, float)
    v = track.valid
    Rb = np.full((len(track), 3, 3), np.nan)
    Rb[v] = matrix_from_quat(track.quat_xyzw[v])
    R_rel = A @ Rb @ rest.R.T @ A.T
    origin0 = A @ rest.t + b  # the body's rest position in the model frame
    t_rel = track.position @ A.T + b - np.einsum("nij,j->ni", R_rel, origin0)
    q = np.full((len(track), 4), np.nan)
    q[v] = quat_from_matrix(R_rel[v])
    meta = dict(track.meta)
    meta.update(
        frame="model (relative to rest)",
        registration="rest window" if given is None else "given tracker-to-model transform",
        rest_spread_m=float(rest.rms_residual),
        rest_samples=int(rest_window(track, rest_window_s).sum()) if not given_rest else track.meta.get("rest_samples", 0),
    )
    t_rel = np.where(v[:, None], t_rel, np.nan)
    return PoseTrack(track.t.copy(), t_rel, q, v.copy(), track.clock, track.source, track.name, meta)


def track_pose6(track: PoseTrack) -> Pose6:
    """The (n,) stack of 6-DoF poses of a registered track (NaN where invalid)."""
    ypr = np.full((len(track), 3), np.nan)
    v = track.valid
    ypr[v] = ypr_from_matrix(matrix_from_quat(track.quat_xyzw[v]))
    return Pose6(track.position.copy(), ypr)


def pose_columns(track: PoseTrack, keep_lost: bool = False) -> dict[str, np.ndarray]:
    """The truth file's columns of a registered track: ``t_s`` and the 6 DoF in mm and degrees
    (lost frames dropped, or kept as NaN with ``keep_lost``)."""
    v = np.ones(len(track), bool) if keep_lost else track.valid
    cols = {"t_s": track.t[v]}
    vals = track_pose6(track).to_mm_deg()[v]
    for k, name in enumerate(Pose6.COLUMNS):
        cols[name] = vals[:, k]
    return cols
