"""The virtual motion tracker: the marker rigid body as OptiTrack Motive would export it.

Each tracker frame (``rate_Hz``, 120 by default) sees the truth's marker points at the event time
the frame stands for, adds Gaussian noise of ``noise_mm`` (0.19 mm, the paper's registration
precision, σ per axis per marker), fits the rigid body to them (as Motive does: the body's pivot is
the bulb centre at rest and its axes are the model's) and expresses it in the tracker's world frame
(seeded placement, y up as in Motive). The take has its own clock: the take starts at scenario time
``take_start_s`` (seeded, before the scenario) and the tracker reports with ``latency_s``, so an
event at scenario time t appears at take time ``t − take_start_s + latency_s``
(:attr:`TrackerStream.clock_offset_s`). Frames are lost at random (``lost_fraction``, in short
bursts), written as blank cells.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softphantom.pose import RigidTransform, matrix_from_ypr, quat_from_matrix, rigid_fit


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker settings (SI, seeded): None = drawn from ``seed`` (take start uniform in
    [−0.6, −0.2] s, latency uniform in [4, 12] ms)."""

    rate_Hz: float = 120.0
    noise_mm: float = 0.19
    lost_fraction: float = 0.01
    take_start_s: float | None = None
    latency_s: float | None = None
    seed: int = 0
    body: str = "bip"


@dataclass(frozen=True, eq=False)
class TrackerStream:
    """``t_take`` (n,) s take clock; ``position`` (n, 3) m and ``quat_xyzw`` (n, 4) of the body in
    the tracker frame (NaN when lost); ``markers`` (n, k, 3) m noisy marker points in the tracker
    frame; ``valid`` (n,); ``t_event`` (n,) scenario time each frame stands for;
    ``tracker_from_model`` the placement; ``take_start_s``, ``latency_s``."""

    t_take: np.ndarray
    position: np.ndarray
    quat_xyzw: np.ndarray
    markers: np.ndarray
    valid: np.ndarray
    t_event: np.ndarray
    tracker_from_model: RigidTransform
    take_start_s: float
    latency_s: float
    config: TrackerConfig

    @property
    def clock_offset_s(self) -> float:
        """Take time minus scenario time of the same event (s)."""
        return self.latency_s - self.take_start_s


def simulate_tracker(truth, config: TrackerConfig = TrackerConfig()) -> TrackerStream:
    """Tracker frames over the scenario of ``truth`` (a :class:`~softphantom.virtual.truth.Truth`)."""
    rng = np.random.default_rng([config.seed, 3])
    take0 = rng.uniform(-0.6, -0.2) if config.take_start_s is None else float(config.take_start_s)
    lat = rng.uniform(0.004, 0.012) if config.latency_s is None else float(config.latency_s)
    yaw, tilt = rng.uniform(-np.pi, np.pi), rng.uniform(-0.1, 0.1)
    # Motive is y-up: model z (up) → tracker y; model y → tracker −z; then a seeded turn and place
    A = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    R = matrix_from_ypr(np.array([0.0, tilt, yaw])) @ A  # roll (about y, the tracker's up) = yaw here
    T = RigidTransform(R, np.array([0.2, 0.9, -0.4]) + rng.uniform(-0.2, 0.2, 3))
    dur = truth.scenario.duration_s
    t_take = np.arange(0.0, dur - take0 + lat, 1.0 / config.rate_Hz)
    t_event = t_take + take0 - lat
    ts = truth.sample(np.clip(t_event, 0.0, dur))
    rest = truth.rest_markers
    mk_model = ts.markers + rng.normal(scale=config.noise_mm * 1e-3, size=ts.markers.shape)
    fit = rigid_fit(rest, mk_model)  # body (model coordinates) relative to rest
    Rw = np.einsum("ij,njk->nik", T.R, fit.R)
    pos = np.einsum("ij,nj->ni", T.R, fit.t) + T.t
    quat = quat_from_matrix(Rw)
    mk_world = np.einsum("ij,nkj->nki", T.R, mk_model) + T.t
    n = len(t_take)
    valid = np.ones(n, bool)
    if config.lost_fraction > 0:
        n_bursts = rng.binomial(n, config.lost_fraction / 2.0)
        for s in rng.integers(0, n, n_bursts):
            valid[s:s + rng.integers(1, 4)] = False
        valid[: int(0.5 * config.rate_Hz)] = True  # a clean rest window at the start of the take
    pos[~valid] = np.nan
    quat[~valid] = np.nan
    mk_world[~valid] = np.nan
    return TrackerStream(t_take, pos, quat, mk_world, valid, t_event, T, float(take0), float(lat), config)


def write_motive_csv(stream: TrackerStream, path, marker_names=(), take_name: str = "virtual") -> Path:
    """Write a Motive 1.23-style CSV export: metadata row, blank row, Type/Name/ID/property/axis
    rows, then Frame, Time (Seconds), rigid body Rotation X Y Z W, Position X Y Z (metres), then
    each marker's Position X Y Z; lost frames as blank cells; CRLF line ends, as Motive writes."""
    path = Path(path)
    body = stream.config.body
    k = stream.markers.shape[1]
    names = list(marker_names) or [f"Marker{i + 1}" for i in range(k)]
    types = ["Rigid Body"] * 7 + ["Rigid Body Marker"] * (3 * k)
    nm = [body] * 7 + [f"{body}:{names[i]}" for i in range(k) for _ in range(3)]
    ids = ["1"] * 7 + [f"1:{i + 1}" for i in range(k) for _ in range(3)]
    props = ["Rotation"] * 4 + ["Position"] * 3 + ["Marker Position"] * (3 * k)
    axes = ["X", "Y", "Z", "W", "X", "Y", "Z"] + ["X", "Y", "Z"] * k
    lines = [
        f"Format Version,1.23,Take Name,{take_name},Take Notes,,Capture Frame Rate,{stream.config.rate_Hz:.6f},"
        f"Export Frame Rate,{stream.config.rate_Hz:.6f},Capture Start Time,2024-01-01 12.00.00.000 PM,"
        f"Total Frames in Take,{len(stream.t_take)},Total Exported Frames,{len(stream.t_take)},"
        "Rotation Type,Quaternion,Length Units,Meters,Coordinate Space,Global",
        "",
        ",Type," + ",".join(types),
        ",Name," + ",".join(nm),
        ",ID," + ",".join(ids),
        ",," + ",".join(props),
        "Frame,Time (Seconds)," + ",".join(axes),
    ]
    f = lambda v: "" if not np.isfinite(v) else f"{v:.6f}"  # noqa: E731
    for i in range(len(stream.t_take)):
        vals = list(stream.quat_xyzw[i]) + list(stream.position[i]) + list(stream.markers[i].reshape(-1))
        lines.append(f"{i},{stream.t_take[i]:.6f}," + ",".join(f(v) for v in vals))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path
