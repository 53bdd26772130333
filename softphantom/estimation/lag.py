"""Compensation of the tubes' pneumatic lag: the cavity pressures of now from the transducers'.

Each arm's transducer sees the cavity's equilibrium pressure through its tube, a distributed RC
line (:mod:`softphantom.sensing.tube`): ≈ 0.1 s of delay for the paper's 12 m × 1.2 mm tubes. The
compensator is a Kalman filter per arm on a few-state model of that line: the line's two slowest
first-order stages and one stage carrying the rest of its Elmore delay, driven by the cavity
pressure, which is modelled as a constant-velocity signal (white noise on its second derivative;
a steady ramp is followed without lag).

**One state, a few gains.** How fast the cavity pressure may change is not known in advance: a
quiet filter (small process noise) is late when a push starts, a fast one is noisy at rest. The
filter keeps one state per arm and switches its steady-state gain between :data:`NOISE_GAIN_LEVELS`
(the process noise of each level tuned so that its noise gain is the stated one) on the evidence of
the innovations: their running means (:data:`INNOVATION_MEMORY`), in units of their standard
deviations at rest and RMS over the arms, above each of the thresholds (:data:`FALSE_RISE`,
:data:`Z_LEVELS`) raise the level by one, for all arms at once (a load moves every arm); the level
falls back by one per sample. The state
is shared, so no quieter filter is left behind during a push to catch up (and overshoot) when the
level falls. The gains are solved once per sample interval and cached, so a step is one small
matrix product.

**Noise gain.** At each level the filter is linear in the measured pressures: white noise on a
transducer comes out multiplied by the level's noise gain g = ‖h‖₂ (the RMS of its impulse
response). At rest the lowest level holds (:data:`DEFAULT_NOISE_GAIN`); the highest is reached only
while the innovations are many standard deviations off (a step).

The compensated pressure replaces ``dp`` of the arms, and ``dV`` follows by Boyle over the arm's
V_T; the internal cavities' pressures (no tube lag) pass through. After a gap in the board clock of
more than :data:`MAX_GAP_S`, a clock that runs backwards, or a sample that is not ``ok``, the filter
restarts at rest on the next good sample.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import numpy as np

from softphantom.errors import UserError

MODES = ("off", "model")
"""``--lag-compensation``: ``off`` the transducers' pressures as they are; ``model`` compensated
with the tube model of the bench."""

DEFAULT_NOISE_GAIN = 1.2
"""White pressure noise is multiplied by this (RMS) through the compensation at rest."""

NOISE_GAIN_LEVELS = (1.2, 2.0, 3.0, 4.5, 7.0)
"""The noise gains of the filter's levels, the quietest (at rest) first; the highest follows a load
step (its 50 % point within 30 ms at 19.2 Hz frames)."""

FALSE_RISE = 0.02
"""The share of samples at rest whose innovations' running means rise above the quietest level by
chance (their RMS over the arms in standard deviations at rest: 1.71 with four arms, 2.33 with one)."""

Z_LEVELS = (1.0, 4 / 3, 2.0, 10 / 3)
"""The thresholds of the levels above the quietest, in multiples of the first (:data:`FALSE_RISE`)."""

INNOVATION_MEMORY = 0.5
"""The weight of the newest innovation in their running mean (exponential)."""

LEARN_SAMPLES = 16
"""Samples after a (re)start (at rest) from which the innovations' standard deviation is first taken."""

RATE_SAMPLES = 200
"""Then it follows the noise at rest with this memory (samples)."""

MIN_TAU_S = 0.010
"""Compensation is on by default where the tubes' time constant exceeds this (10 ms: 3 m of the
paper's tube is 7 ms, a sixth of a 77 Hz frame's interval)."""

MAX_GAP_S = 0.5
"""A longer hole in the board clock restarts the filter at rest (the line has settled by then)."""

N_STAGES = 2
"""The line's slowest stages modelled one by one; one more stage carries the rest of the delay."""


def _cascade(taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, G) of the continuous model: state [u, u̇, s_1 … s_m], u̇ = v, v̇ = w, s_1' = (u − s_1)/τ_1,
    s_j' = (s_{j−1} − s_j)/τ_j; ``G`` the noise input (on v̇)."""
    m = len(taus)
    n = 2 + m
    F = np.zeros((n, n))
    F[0, 1] = 1.0
    prev = 0
    for j, tau in enumerate(taus):
        i = 2 + j
        F[i, prev] = 1.0 / tau
        F[i, i] = -1.0 / tau
        prev = i
    G = np.zeros(n)
    G[1] = 1.0
    return F, G


def _discrete(taus: np.ndarray, dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, Q_d) of the model over ``dt`` with process-noise intensity ``q`` (Van Loan)."""
    from scipy.linalg import expm

    F, G = _cascade(taus)
    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = q * np.outer(G, G)
    M[n:, n:] = F.T
    E = expm(M * dt)
    A = E[n:, n:].T
    Qd = A @ E[:n, n:]
    return A, 0.5 * (Qd + Qd.T)


def _steady(A: np.ndarray, Qd: np.ndarray) -> tuple[np.ndarray, float]:
    """Steady-state Kalman gain for a measurement of the last state with unit noise variance, and
    the innovation's variance (in units of the measurement noise's)."""
    from scipy.linalg import solve_discrete_are

    n = A.shape[0]
    C = np.zeros((1, n))
    C[0, -1] = 1.0
    P = solve_discrete_are(A.T, C.T, Qd + 1e-15 * np.eye(n), np.eye(1))
    S = float((C @ P @ C.T)[0, 0]) + 1.0
    return (P @ C.T).ravel() / S, S


def _steady_gain(A: np.ndarray, Qd: np.ndarray) -> np.ndarray:
    return _steady(A, Qd)[0]


def filter_noise_gain(A: np.ndarray, K: np.ndarray) -> float:
    """‖h‖₂ of the filter y → û (the first state after the update): √Σ h_k²."""
    from scipy.linalg import solve_discrete_lyapunov

    n = A.shape[0]
    C = np.zeros((1, n))
    C[0, -1] = 1.0
    phi = (np.eye(n) - np.outer(K, C)) @ A
    X = solve_discrete_lyapunov(phi, np.outer(K, K))
    return math.sqrt(max(float(X[0, 0]), 0.0))


def tune(taus: np.ndarray, dt: float, noise_gain: float = DEFAULT_NOISE_GAIN) -> float:
    """The process-noise intensity q (per unit measurement variance) whose steady filter has
    the noise gain ``noise_gain`` at ``dt`` (bisection in log q; the gain grows with q)."""
    if not noise_gain > 1.0:
        raise UserError(f"lag compensation noise gain: must be > 1, got {noise_gain!r}")
    return _tune(tuple(float(t) for t in np.round(np.asarray(taus, float), 12)), round(float(dt), 9),
                 float(noise_gain))


@functools.lru_cache(maxsize=256)
def _tune(taus: tuple, dt: float, noise_gain: float) -> float:
    def gain(lq: float) -> float:
        A, Qd = _discrete(np.array(taus), dt, 10.0**lq)
        return filter_noise_gain(A, _steady_gain(A, Qd))

    lo, hi = -6.0, 14.0
    if gain(hi) < noise_gain:
        return 10.0**hi
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if gain(mid) < noise_gain:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-3:
            break
    return 10.0**lo


@dataclasses.dataclass(frozen=True)
class TubeModel:
    """The per-arm tube time constants the compensation uses: ``tau_s`` (arms,) the Elmore delay
    of each arm's line; ``stages_s`` (arms, N_STAGES + 1) its reduced cascade; ``source`` where
    the τ come from (``"tube"``: the bench's length, bore, cavities and dead volume;
    ``"calibrated"``: a calibration's fit)."""

    tau_s: tuple[float, ...]
    stages_s: tuple[tuple[float, ...], ...]
    source: str = "tube"

    @classmethod
    def of_bench(cls, bench) -> "TubeModel":
        """The tubes of a :class:`~softphantom.sensing.bench.BenchConfig`: each arm's line from the
        tube's length × bore (its length scaled by the calibrated tube volume factor), the arm's
        cavity and the dead volume; a calibrated τ per arm (``bench.tube_tau_s``) rescales its line."""
        from softphantom.sensing.tube import TubeLine

        f = float(getattr(bench, "tube_volume_factor", 1.0))
        cal = tuple(getattr(bench, "tube_tau_s", ()) or ())
        taus, stages = [], []
        for i, vc in enumerate(bench.cavity_volumes_m3):
            line = TubeLine.of(bench.tube_length_m * f, bench.tube_id_m, vc, bench.p0_Pa, bench.v_dead_m3)
            red = line.reduced(N_STAGES)
            if cal:
                red = red * (cal[i] / line.elmore_s)  # same shape of line, the fitted delay
            taus.append(float(red.sum()))
            stages.append(tuple(float(t) for t in red))
        return cls(tuple(taus), tuple(stages), "calibrated" if cal else "tube")

    def to_meta(self) -> dict:
        return {"tube_tau_ms": [round(t * 1e3, 3) for t in self.tau_s], "tube_tau_source": self.source}


class LagCompensator:
    """The compensation of every arm of a bench (see the module docstring): ``apply(m)`` gives
    the measurement with the arms' ``dp`` and ``dV`` of now. ``v_total_m3`` (arms,) V_T for Boyle,
    ``p0_Pa`` the ambient pressure; ``noise_gain`` the quietest level's noise gain (at rest),
    ``levels`` the faster levels' (those above ``noise_gain``; default :data:`NOISE_GAIN_LEVELS`)."""

    def __init__(self, tubes: TubeModel, v_total_m3, p0_Pa: float, noise_gain: float = DEFAULT_NOISE_GAIN,
                 levels: tuple[float, ...] = NOISE_GAIN_LEVELS):
        self.tubes = tubes
        self.v_total = np.asarray(v_total_m3, float)
        self.p0 = float(p0_Pa)
        self.target_gain = float(noise_gain)
        self.levels = (self.target_gain, *sorted(float(g) for g in levels if g > self.target_gain * 1.05))
        self._stages = [np.asarray(s, float) for s in tubes.stages_s]
        self._n = 2 + len(self._stages[0])
        from scipy.special import chdtri  # the χ² quantile (scipy.stats takes a second to import)

        na = len(self._stages)
        self._z = np.sqrt(chdtri(na, FALSE_RISE) / na) * np.asarray(Z_LEVELS)
        self._flat_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._x: np.ndarray | None = None  # (arms·n,): every arm's state
        self._t: float | None = None
        self._var: np.ndarray | None = None  # (arms,) the innovations' variance at rest
        self._mean: np.ndarray | None = None  # (arms,) their running mean
        self._n_rest = 0
        self.level = 0
        self.dt_s: float | None = None
        self.restarts = 0
        self.cost_s = 0.0  # time spent in apply(), the filters' set-up (setup_s) excluded
        self.setup_s = 0.0
        self.samples = 0
        self.raised = 0  # samples above the quietest level

    @classmethod
    def for_bench(cls, bench, noise_gain: float = DEFAULT_NOISE_GAIN) -> "LagCompensator":
        n = len(bench.cavity_volumes_m3)
        return cls(TubeModel.of_bench(bench), bench.chain().v_total_m3[:n], bench.p0_Pa, noise_gain)

    def _solve(self, dtk: float):
        """(A (arms·n)² block-diagonal, K (levels, arms·n), √S (levels, arms)) at ``dtk``: the
        prediction, each level's gain and its innovation's standard deviation per unit noise."""
        a, n = len(self._stages), self._n
        A = np.zeros((a * n, a * n))
        K = np.zeros((len(self.levels), a * n))
        sd = np.zeros((len(self.levels), a))
        for i, st in enumerate(self._stages):
            for j, g in enumerate(self.levels):
                Ai, Qd = _discrete(st, dtk, tune(st, dtk, g))
                k, S = _steady(Ai, Qd)
                A[i * n:(i + 1) * n, i * n:(i + 1) * n] = Ai  # the same at every level (q enters Q only)
                K[j, i * n:(i + 1) * n] = k
                sd[j, i] = math.sqrt(S)
        return A, K, sd

    def _flat(self, dt: float):
        key = int(round(dt * 2e4))  # a board's frames are regular to a few µs: 50 µs bins
        got = self._flat_cache.get(key)
        if got is None:
            t0 = time.perf_counter()
            dtk = max(key, 1) / 2e4
            got = self._solve(dtk)
            self._flat_cache[key] = got
            if self.dt_s is None:
                self.dt_s = dtk
            self.setup_s += time.perf_counter() - t0
        return got

    def prepare(self, dt_s: float) -> None:
        """Set the filters up for sample interval ``dt_s`` now (else on the first samples: ≈ 0.5 s)."""
        self._flat(float(dt_s))

    def noise_gain(self, dt_s: float) -> tuple[float, float]:
        """(rest, fastest): the largest noise gain over the arms of the quietest and the fastest level
        at ``dt_s``."""
        A, K, _ = self._flat(float(dt_s))
        n = self._n
        out = []
        for j in (0, len(self.levels) - 1):
            out.append(max(filter_noise_gain(A[i * n:(i + 1) * n, i * n:(i + 1) * n], K[j, i * n:(i + 1) * n])
                           for i in range(len(self._stages))))
        return out[0], out[1]

    def reset(self) -> None:
        """Forget the state: the next sample restarts the filter at rest."""
        self._x = None
        self._t = None

    def filter(self, t_s: float, dp_Pa: np.ndarray) -> np.ndarray:
        """The compensated arm pressures (Pa) for the transducers' ``dp_Pa`` at board time ``t_s``."""
        y = np.asarray(dp_Pa, float)
        dt = None if self._t is None else t_s - self._t
        n = self._n
        if self._x is None or dt is None or not (0.0 < dt <= MAX_GAP_S):
            if self._x is not None:
                self.restarts += 1
            x = np.repeat(y[:, None], n, axis=1)
            x[:, 1] = 0.0
            self._x = x.ravel()
            self._t = t_s
            self._var, self._mean, self._n_rest, self.level = np.zeros(len(y)), np.zeros(len(y)), 0, 0
            return y.copy()
        A, K, _ = self._flat(dt)
        xp = A @ self._x
        e = y - xp[n - 1::n]  # the innovations: each arm's reading against its prediction
        self._mean += INNOVATION_MEMORY * (e - self._mean)
        if self._n_rest < LEARN_SAMPLES:  # the first samples (at rest): learn the innovations' noise
            self._n_rest += 1
            self._var += (e * e - self._var) / self._n_rest
            want = 0
        else:
            sd = np.sqrt(self._var * (INNOVATION_MEMORY / (2.0 - INNOVATION_MEMORY))) + 1e-12
            zz = self._mean / sd
            z = math.sqrt(float(zz @ zz) / len(zz))  # a load moves every arm: their evidence adds
            want = min(int(np.searchsorted(self._z, z)), len(self.levels) - 1)
            if want == 0 and self.level == 0:  # at rest: follow the noise level
                self._var += (np.minimum(e * e, 9.0 * self._var) - self._var) * (1.0 / RATE_SAMPLES)
        self.level = max(want, self.level - 1)
        if self.level:
            self.raised += 1
        x = xp + K[self.level] * np.repeat(e, n)
        self._x = x
        self._t = t_s
        return x[::n].copy()

    def apply(self, m):
        """The measurement ``m`` with its arms' pressures and volumes compensated."""
        t0, s0 = time.perf_counter(), self.setup_s
        dp0 = m.dp
        if m.status != "ok" or not math.isfinite(float(dp0.sum())):
            self.reset()
            return m
        dp = np.maximum(self.filter(float(m.t_board), dp0), -0.9 * self.p0)
        dV = self.v_total * (self.p0 / (self.p0 + dp) - 1.0)  # Boyle over cavity + tube
        out = type(m)(m.t, m.seq, m.t_board, m.raw, m.osr, dp, dV, m.p_urethra, m.status, m.pressures_Pa)
        self.cost_s += time.perf_counter() - t0 - (self.setup_s - s0)
        self.samples += 1
        return out

    def meta(self) -> dict:
        """What the estimate file records: the mode, the τ in use, the noise gains at rest and at the
        fastest level."""
        return {"lag_compensation": "model", **self.tubes.to_meta(), "lag_noise_gain_rest": self.target_gain,
                "lag_noise_gain_max": self.levels[-1]}


MAX_TAU_S = 2.0
"""A tube whose time constant exceeds this is no bench's (a 12 m tube: 0.1 s; 2 s is ≈ 53 m of it)."""


def check_tubes(bench) -> TubeModel:
    """The bench's tube model, or a one-line :class:`UserError` (exit 2) when a τ is not physical
    for the stated tube: a calibrated τ outside the range its length, bore and cavity allow
    (:attr:`~softphantom.sensing.tube.TubeLine.tau_range_s`), or any τ above :data:`MAX_TAU_S`."""
    from softphantom.sensing.tube import TubeLine

    tubes = TubeModel.of_bench(bench)
    f = float(getattr(bench, "tube_volume_factor", 1.0))
    stated = f"tube {bench.tube_length_m:g} m × {bench.tube_id_m * 1e3:g} mm"
    for name, vc, tau in zip(bench.arm_names, bench.cavity_volumes_m3, tubes.tau_s):
        line = TubeLine.of(bench.tube_length_m * f, bench.tube_id_m, vc, bench.p0_Pa, bench.v_dead_m3)
        lo, hi = line.tau_range_s
        if tubes.source == "calibrated" and not lo <= tau <= hi:
            raise UserError(f"tube τ of {name}: {tau * 1e3:.4g} ms (calibrated) is outside {lo * 1e3:.3g} … "
                            f"{hi * 1e3:.4g} ms, the range of the stated {stated}: check the tube length and bore")
        if tau > MAX_TAU_S:
            raise UserError(f"tube τ of {name}: {tau:.3g} s for the stated {stated} is beyond any bench's "
                            f"({MAX_TAU_S:g} s): check the tube length and bore")
    return tubes


def lag_compensation(mode: str | None, bench, *, tube_missing: str | None = None, source: str = "the source",
                     noise_gain: float = DEFAULT_NOISE_GAIN) -> tuple[LagCompensator | None, dict, str | None]:
    """The compensator a run uses: (compensator or None, metadata for the estimate file, a warning
    line or None). ``mode`` ``"model"``, ``"off"``, or None (default: on where the tubes' τ exceeds
    :data:`MIN_TAU_S`); ``tube_missing`` the tube setting a recording lacks (compensation off, with
    the warning naming it). A τ that is not physical for the stated tube raises (one line)."""
    if mode is not None and mode not in MODES:
        raise UserError(f"--lag-compensation: expected {' or '.join(MODES)}, got {mode!r}")
    if mode == "off" or bench is None:
        return None, {"lag_compensation": "off"}, None
    if tube_missing:
        return None, {"lag_compensation": "off", "lag_compensation_note": f"no {tube_missing}"}, (
            f"warning: lag compensation off: {source} has no {tube_missing} (its tube's lag cannot be modelled)")
    tubes = check_tubes(bench)
    if mode is None and max(tubes.tau_s) < MIN_TAU_S:
        return None, {"lag_compensation": "off", **tubes.to_meta()}, None
    n = len(bench.cavity_volumes_m3)
    comp = LagCompensator(tubes, bench.chain().v_total_m3[:n], bench.p0_Pa, noise_gain)
    return comp, comp.meta(), None


class LagCompensated:
    """An estimator whose measurements are compensated first (:class:`LagCompensator`); the
    compensation's time is part of each estimate's ``step_time``. Everything else is the inner
    estimator's."""

    def __init__(self, estimator, compensator: LagCompensator):
        self._inner = estimator
        self.compensator = compensator

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def step(self, m, *args, **kw):
        t0 = time.perf_counter()
        mc = self.compensator.apply(m)
        spent = time.perf_counter() - t0
        e = self._inner.step(mc, *args, **kw)
        return dataclasses.replace(e, step_time=e.step_time + spent)

    def __enter__(self):
        self._inner.__enter__()
        return self

    def __exit__(self, *exc):
        return self._inner.__exit__(*exc)


def compensated(estimator, compensator: LagCompensator | None):
    """``estimator`` with the lag compensation in front (itself when ``compensator`` is None)."""
    return estimator if compensator is None else LagCompensated(estimator, compensator)
