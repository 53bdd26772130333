"""Each tube's time constant, fitted from a session with known loads (``calibrate``; docs/calibration.md).

The known loads are on the recording's clock, so their timing against the transducers' pressures
is the tubes' alone (the tracker's clock offset does not enter). Per arm, the transducer pressure
is modelled as an offset plus the known force's three components, each passed through the arm's
line (:class:`~softphantom.sensing.tube.TubeLine`, its delay scaled to τ), times a sensitivity;
the sensitivities and offset are linear least squares for each τ, and τ minimises the residual
(a grid in log τ over :data:`SCALE_RANGE` × the tube's, refined by a parabola). A step (a weight
hung on) or a push of known force will do; the load must move faster than a few τ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.sensing.tube import TubeLine

SCALE_RANGE = (1 / 4, 4.0)
"""τ searched between these multiples of the stated tube's."""
N_GRID = 49
MIN_MOVE_N = 0.2
"""A session whose known force moves less than this (N) says nothing about the lag."""


@dataclass(frozen=True)
class TubeFit:
    """``tau_s`` (arms,) the fitted time constants (Elmore delay), ``nominal_s`` the stated tube's,
    ``sd_s`` (arms,) their standard deviations (from the residual's curvature in τ), ``session``."""

    tau_s: np.ndarray
    nominal_s: np.ndarray
    sd_s: np.ndarray
    session: str


def _line(se, vc: float) -> TubeLine:
    return TubeLine.of(se.tube_length_m * se.recorded_tube_factor, se.tube_id_m, vc, se.p0_Pa)


def fit_tube_tau(se) -> TubeFit | None:
    """The tubes' τ of a :class:`~softphantom.calibration.session.Session` with known loads (None
    without them, or when the known force hardly moves)."""
    if se.known_t is None or len(se.t) < 20:
        return None
    t = np.asarray(se.t, float)
    dt = float(np.median(np.diff(t)))
    tu = np.arange(t[0], t[-1], dt)
    force = se.known_at(tu)
    if not np.all(np.isfinite(force)) or np.ptp(force, axis=0).max() < MIN_MOVE_N:
        return None
    nominal = se.tau_s(se.recorded_tube_factor)
    # the transducers' own readings: the session's pressures were de-lagged with the recording's tube
    raw = se.dp - (se.tau_s(1.0)[None, :] * se.dp_rate if se.dp_rate is not None else 0.0)
    scales = np.exp(np.linspace(math.log(SCALE_RANGE[0]), math.log(SCALE_RANGE[1]), N_GRID))
    taus, sds = [], []
    for i, vc in enumerate(se.cavity_m3):
        y = np.interp(tu, t, raw[:, i])
        base = _line(se, float(vc))

        def sse(c: float) -> float:
            line = TubeLine(base.r * c, base.c_cavity, base.c_tube, base.c_dead)  # τ ∝ R: the delay × c
            cols = [np.ones_like(tu)] + [line.ladder_response(force[:, k], dt, 24) for k in range(3)]
            A = np.column_stack(cols)
            coef, *_ = np.linalg.lstsq(A, y, rcond=None)
            r = y - A @ coef
            return float(r @ r)

        e = np.array([sse(c) for c in scales])
        k = int(np.clip(np.argmin(e), 1, N_GRID - 2))
        lx = np.log(scales[k - 1:k + 2])
        a, b, _ = np.polyfit(lx, e[k - 1:k + 2], 2)
        lc = float(np.clip(-b / (2 * a), lx[0], lx[2])) if a > 0 else float(lx[1])
        taus.append(nominal[i] * math.exp(lc))
        # σ² of the residual per sample; SSE(ln c) ≈ SSE_min + a·Δ², so var(ln c) ≈ σ²/a
        s2 = float(e.min()) / max(len(tu) - 4, 1)
        sds.append(taus[-1] * math.sqrt(s2 / a) if a > 0 else math.inf)
    return TubeFit(np.array(taus), nominal, np.array(sds), se.name)


def combine(fits: list[TubeFit]) -> TubeFit | None:
    """One τ per arm from several sessions: the inverse-variance mean (None without any fit)."""
    fits = [f for f in fits if f is not None]
    if not fits:
        return None
    tau = np.array([f.tau_s for f in fits])
    w = 1.0 / np.maximum(np.array([f.sd_s for f in fits]), 1e-6) ** 2
    mean = (w * tau).sum(0) / w.sum(0)
    return TubeFit(mean, fits[0].nominal_s, 1.0 / np.sqrt(w.sum(0)), ", ".join(f.session for f in fits))
