"""A calibration session: one bench recording (the arm pressures and the pressure of every internal
cavity), the tracker's take of the same trial, optionally known loads, and the keyframes chosen
from them.

Checks (each a one-line :class:`~softphantom.errors.UserError`): a recording whose arm or pressure
channels are not the model's, a recording with no rest window at its start, a take whose valid
samples cover less than half of it, a take that does not overlap the recording in time, too few
distinct loads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from softphantom.errors import UserError
from softphantom.records.names import BIP_CAVITIES, pressure_columns
from softphantom.sensing.pneumatics import tube_time_constant_s

#: Rest window at the start of a recording: in its first REST_S seconds every arm's pressure has a
#: standard deviation ≤ REST_MAX_PA and a slope ≤ REST_MAX_SLOPE_PA_S (the tare's limits).
REST_S = 0.5
REST_MAX_PA = 25.0
REST_MAX_SLOPE_PA_S = 20.0
#: Keyframe candidates every CANDIDATE_DT_S; a pressure "moves" above MOVING_PA.
CANDIDATE_DT_S = 0.1
MOVING_PA = 15.0
#: An internal cavity's pressure is a load axis of the keyframe choice beside the arm pressures:
#: above CAVITY_QUIET_PA (its transducer's noise, the BIP's urethra ±0.1 kPa, is far below) each
#: CAVITY_STEP_PA counts as MOVING_PA of arm pressure. Without it an inflation moves the arm
#: pressures by a few Pa only (an internal load is in equilibrium with itself) and no keyframe
#: would see it.
CAVITY_QUIET_PA = 2e3
CAVITY_STEP_PA = 5e3
#: Smallest pressure noise assumed (Pa): the model is never better than this.
NOISE_FLOOR_PA = 1.0


class CalibrationInputError(UserError):
    """A session that cannot calibrate what was asked (names the file and the problem)."""


@dataclass(frozen=True, eq=False)
class Session:
    """One trial: ``t`` (n,) s host clock, ``dp`` (n, arms) Pa tared arm pressures with the tube lag
    undone, ``p_urethra`` (n,) Pa the urethra's pressure (NaN without one), ``truth_t`` (m,) s
    tracker clock, ``truth_pose`` (m, 6) m and rad (x, y, z, yaw, pitch, roll relative to rest,
    rest-window registration), ``contact`` (3,) m the contact point, ``known_t``/``known_force``
    (k,), (k, 3) N or None, ``name``; the bench's tube, arm cavities and P0; ``cavity_names`` the
    internal cavities and ``pressures`` (n, M) Pa their gauge pressures, in the model's load order
    (None: ``p_urethra`` as the one column of the urethra; :attr:`cavity_pressures_Pa` either way)."""

    name: str
    t: np.ndarray
    dp: np.ndarray
    p_urethra: np.ndarray
    truth_t: np.ndarray
    truth_pose: np.ndarray
    contact: np.ndarray
    p0_Pa: float
    tube_length_m: float
    tube_id_m: float
    cavity_m3: np.ndarray
    dp_noise_Pa: np.ndarray = None  # (arms,) std of the de-lagged pressures in the rest window
    known_t: np.ndarray | None = None
    known_force: np.ndarray | None = None
    recorded_gains: np.ndarray = field(default_factory=lambda: np.ones(4))  # the chain the recording used
    recorded_tube_factor: float = 1.0
    dp_rate: np.ndarray | None = None  # (n, arms) Pa/s the readings' rate, what the de-lag multiplied by τ
    cavity_names: tuple[str, ...] = BIP_CAVITIES
    pressures: np.ndarray | None = None

    @property
    def cavity_pressures_Pa(self) -> np.ndarray:
        """(n, M) Pa the internal cavities' gauge pressures, in :attr:`cavity_names` order."""
        return cavity_pressures(self.p_urethra, self.pressures, self.cavity_names)

    def tau_s(self, tube_factor: float = 1.0) -> np.ndarray:
        """(arms,) each arm's tube time constant (s) with the tube's volume × ``tube_factor`` taken as
        its length (the bore is the supplier's; a tube of unknown length is the usual error):
        τ ∝ length², so a tube 10 % longer lags 21 % more. ``dp`` was de-lagged with ``tau_s(1)``."""
        return np.array([tube_time_constant_s(self.tube_length_m * tube_factor, self.tube_id_m, v, self.p0_Pa)
                         for v in self.cavity_m3])

    @property
    def tube_m3(self) -> float:
        """The tube volume the recording's conversion assumed (length × bore × its factor)."""
        from softphantom.sensing.pneumatics import tube_volume_m3

        return self.recorded_tube_factor * tube_volume_m3(self.tube_length_m, self.tube_id_m)

    def pose_at(self, t: np.ndarray) -> np.ndarray:
        """The tracker pose (6,) per time, linear interpolation; NaN outside the take."""
        t = np.atleast_1d(np.asarray(t, float))
        out = np.full((t.size, 6), np.nan)
        inside = (t >= self.truth_t[0]) & (t <= self.truth_t[-1])
        for k in range(6):
            out[inside, k] = np.interp(t[inside], self.truth_t, self.truth_pose[:, k])
        return out

    def known_at(self, t: np.ndarray) -> np.ndarray | None:
        if self.known_t is None:
            return None
        t = np.atleast_1d(np.asarray(t, float))
        return np.stack([np.interp(t, self.known_t, self.known_force[:, k]) for k in range(3)], axis=1)


def cavity_pressures(p_urethra, pressures, names) -> np.ndarray:
    """(n, M) Pa: ``pressures`` where given, else the BIP's ``p_urethra`` (n,) as the urethra's
    column (the only cavity ``names`` may then hold).

    >>> cavity_pressures(np.array([1.0, 2.0]), None, ("urethra",)).tolist()
    [[1.0], [2.0]]
    >>> cavity_pressures(np.array([1.0, 2.0]), None, ("tumour",))
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: pressures of tumour: not given (a urethra pressure alone is)
    """
    if pressures is not None:
        p = np.asarray(pressures, float)
        if p.ndim != 2 or p.shape[1] != len(names):
            raise UserError(f"pressures of {', '.join(names) or 'no cavity'}: shape {p.shape}, one column each expected")
        return p
    if tuple(names) != BIP_CAVITIES:
        raise UserError(f"pressures of {', '.join(names) or 'no cavity'}: not given (a urethra pressure alone is)")
    return np.asarray(p_urethra, float).reshape(-1, 1)


def check_channels(path, rec, layout) -> np.ndarray:
    """The recording's actuated-cavity pressures (n, M) Pa in the order of ``layout`` (the model's
    :class:`~softphantom.records.channels.ChannelLayout`; None: the recording's own), after checking
    that its volume and pressure channels are the model's (the volume channels in order; the same
    cavities in any order): else a one-line :class:`CalibrationInputError` naming both lists."""
    if layout is not None and tuple(rec.arm_names) != layout.sensing:
        raise CalibrationInputError(f"{path}: arm channels {', '.join(rec.arm_names)} are not the model's "
                                    f"({', '.join(layout.sensing)})")
    have = tuple(rec.cavity_names)
    want = have if layout is None else layout.actuated
    if sorted(have) != sorted(want):
        raise CalibrationInputError(f"{path}: pressure channels {', '.join(pressure_columns(have)) or 'none'} are not "
                                    f"the model's internal cavities' ({', '.join(pressure_columns(want)) or 'none'})")
    return np.asarray(rec.pressures, float)[:, [have.index(c) for c in want]].reshape(len(rec), len(want))


def undo_tube_lag(t: np.ndarray, dp: np.ndarray, tau_s: np.ndarray, window_s: float = 0.15,
                  with_rate: bool = False):
    """The cavity pressure from the transducer's lagged reading: ``p + τ·dp/dt`` (the inverse of the
    first-order tube lag), the derivative from a Savitzky–Golay fit over ``window_s``; with
    ``with_rate`` also that derivative (n, 4) Pa/s."""
    dt = float(np.median(np.diff(t)))
    n = max(5, int(round(window_s / dt)) | 1)
    if len(t) <= n:
        return (dp.copy(), np.zeros_like(dp)) if with_rate else dp.copy()
    smooth = savgol_filter(dp, n, 2, axis=0)
    deriv = savgol_filter(dp, n, 2, deriv=1, delta=dt, axis=0)
    out = smooth + deriv * np.asarray(tau_s)[None, :]
    return (out, deriv) if with_rate else out


def _bench(meta: dict, path: Path):
    from softphantom.sensing.bench import BenchConfig

    try:
        b = BenchConfig.from_meta(meta)
    except UserError as exc:
        raise CalibrationInputError(f"{path}: {exc}") from None
    p0 = float((meta.get("tare") or {}).get("p0_Pa", b.p0_Pa))
    return b, p0


def load_session(recording, truth, contact_m, known_loads=None, name: str | None = None,
                 tube_length_m: float | None = None, tube_id_mm: float | None = None,
                 body: str | None = None, layout=None) -> Session:
    """Read a recording (``softphantom acquire`` / ``virtual run``), a take (any truth
    ``evaluate`` reads: truth CSV, Motive CSV, ROS bag, mcap), optional known loads (a CSV with
    ``t_s, force_x_N, force_y_N, force_z_N`` on the recording's clock) and check them.
    ``layout``: the model's :class:`~softphantom.records.channels.ChannelLayout`, which the
    recording's channels must be (None: the recording's own)."""
    from softphantom.evaluation import read_truth
    from softphantom.evaluation.files import read_table
    from softphantom.sensing.recording import read_recording

    rec_path = Path(recording)
    rec = read_recording(rec_path)
    if len(rec) < 20:
        raise CalibrationInputError(f"{rec_path}: {len(rec)} samples, too short to calibrate")
    p_all = check_channels(rec_path, rec, layout)
    cav_names = tuple(rec.cavity_names) if layout is None else layout.actuated
    ok = (np.array([s == "ok" for s in rec.status]) & np.all(np.isfinite(rec.dp), axis=1)
          & np.all(np.isfinite(p_all), axis=1))
    t, dp, pu, pc = rec.t[ok], rec.dp[ok], rec.p_urethra[ok], p_all[ok]
    rest = t <= t[0] + REST_S
    if rest.sum() < 5:
        raise CalibrationInputError(f"{rec_path}: no rest window at the start ({int(rest.sum())} samples in the "
                                    f"first {REST_S} s): record the phantom untouched first")
    slope = np.polyfit(t[rest] - t[0], dp[rest], 1)[0]
    std = np.std(dp[rest], axis=0)
    if np.any(np.abs(slope) > REST_MAX_SLOPE_PA_S) or np.any(std > REST_MAX_PA):
        k = int(np.argmax(np.abs(slope) / REST_MAX_SLOPE_PA_S + std / REST_MAX_PA))
        raise CalibrationInputError(
            f"{rec_path}: no rest window at the start ({rec.arm_names[k]} moves {slope[k]:+.0f} Pa/s, std {std[k]:.0f} Pa in "
            f"the first {REST_S} s; limits {REST_MAX_SLOPE_PA_S:.0f} Pa/s, {REST_MAX_PA:.0f} Pa): "
            "record the phantom untouched first")
    bench, p0 = _bench(rec.meta, rec_path)
    length = tube_length_m if tube_length_m is not None else bench.tube_length_m
    bore = tube_id_mm * 1e-3 if tube_id_mm is not None else bench.tube_id_m
    cav = np.asarray(bench.cavity_volumes_m3)
    tau = np.array([tube_time_constant_s(length, bore, v, p0) for v in cav])
    dp, rate = undo_tube_lag(t, dp, tau, with_rate=True)
    noise = np.maximum(np.std(dp[rest], axis=0), NOISE_FLOOR_PA)

    tr_path = Path(truth)
    series = read_truth(tr_path, body=body)
    n_all = series.meta.get("lost_frames", 0) + len(series.t)
    if n_all and len(series.t) < 0.5 * n_all:
        raise CalibrationInputError(f"{tr_path}: the body is lost in {series.meta.get('lost_frames')} of "
                                    f"{n_all} frames (more than half): fix the tracking before calibrating")
    if len(series.t) < 10:
        raise CalibrationInputError(f"{tr_path}: {len(series.t)} valid tracker samples, too few")
    pose = np.concatenate([series.pose.xyz, series.pose.ypr], axis=1)
    kt = kf = None
    if known_loads is not None:
        kp = Path(known_loads)
        tab = read_table(kp)
        cols = ("t_s", "force_x_N", "force_y_N", "force_z_N")
        missing = [c for c in cols if c not in tab.columns]
        if missing:
            raise CalibrationInputError(f"{kp}: known loads need columns {', '.join(cols)}; missing {', '.join(missing)}")
        kt = np.asarray(tab.columns["t_s"], float)
        kf = np.stack([np.asarray(tab.columns[c], float) for c in cols[1:]], axis=1)
        good = np.isfinite(kt) & np.all(np.isfinite(kf), axis=1)
        kt, kf = kt[good], kf[good]
        if len(kt) < 2 or kt[-1] < t[0] or kt[0] > t[-1]:
            raise CalibrationInputError(f"{kp}: known loads do not overlap the recording "
                                        f"({t[0]:.2f}–{t[-1]:.2f} s)")
    return Session(name or rec_path.stem, t, dp, pu, series.t.copy(), pose, np.asarray(contact_m, float),
                   p0, length, bore, cav, noise, kt, kf, np.asarray(bench.gains), bench.tube_volume_factor, rate,
                   cav_names, pc)


def cavity_load_axes(p_Pa: np.ndarray) -> np.ndarray:
    """Internal-cavity pressures (n, M) Pa as keyframe-choice coordinates in arm-pressure Pa:
    0 within ±``CAVITY_QUIET_PA``, then ``MOVING_PA`` per ``CAVITY_STEP_PA``.

    >>> cavity_load_axes(np.array([[1.5e3, -12e3]])).tolist()
    [[0.0, -30.0]]
    """
    p = np.asarray(p_Pa, float)
    return np.sign(p) * np.maximum(np.abs(p) - CAVITY_QUIET_PA, 0.0) * (MOVING_PA / CAVITY_STEP_PA)


def select_keyframes(session: Session, max_keyframes: int = 16, rest_keyframes: int = 1) -> np.ndarray:
    """Times (s) of distinct loads: candidates every ``CANDIDATE_DT_S`` where the loads move,
    chosen by farthest-point sampling in the space of the arm pressures and the internal cavities'
    (:func:`cavity_load_axes`; so a hold is not counted twice), plus ``rest_keyframes`` at rest.
    Raises when fewer than 3 distinct loads."""
    t, dp, pc = session.t, session.dp, session.cavity_pressures_Pa
    grid = np.arange(t[0] + REST_S, t[-1], CANDIDATE_DT_S)
    P = np.stack([np.interp(grid, t, dp[:, k]) for k in range(dp.shape[1])]
                 + [cavity_load_axes(np.interp(grid, t, pc[:, j])) for j in range(pc.shape[1])], axis=1)
    moving = np.linalg.norm(P, axis=1) > MOVING_PA
    cand, Pc = grid[moving], P[moving]
    if len(cand) < 3:
        raise CalibrationInputError(
            f"session {session.name}: the arm pressures exceed {MOVING_PA:.0f} Pa at {len(cand)} instants: "
            "too few distinct loads to calibrate (push the phantom in several directions)")
    chosen = [int(np.argmax(np.linalg.norm(Pc, axis=1)))]
    d = np.linalg.norm(Pc - Pc[chosen[0]], axis=1)
    while len(chosen) < min(max_keyframes, len(cand)):
        j = int(np.argmax(d))
        if d[j] < MOVING_PA:
            break
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(Pc - Pc[j], axis=1))
    if len(chosen) < 3:
        raise CalibrationInputError(f"session {session.name}: only {len(chosen)} distinct loads "
                                    f"(pressure patterns closer than {MOVING_PA:.0f} Pa): push in several directions")
    rest = list(np.linspace(t[0] + 0.1, t[0] + REST_S - 0.05, rest_keyframes)) if rest_keyframes else []
    return np.sort(np.concatenate([rest, cand[chosen]]))
