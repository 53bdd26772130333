"""Pneumatics of one sensing arm: tube volume, Boyle p→V, loss factor, thermal drift, tube lag.

Every function is a free function over floats / numpy arrays in SI units. Derivations are in
docs/sensing.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError

AIR_VISCOSITY_PA_S = 1.81e-5
"""Dynamic viscosity of air at 20 °C (Pa·s)."""

ROOM_TEMPERATURE_K = 293.15


def _finite(name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(a)):
        raise UserError(f"{name}: not finite ({a.ravel()[~np.isfinite(a.ravel())][0]})")
    return a


def _positive(name: str, x) -> float:
    v = float(x)
    if not math.isfinite(v) or v <= 0:
        raise UserError(f"{name} must be a positive number, got {x!r}")
    return v


def tube_volume_m3(length_m: float, inner_diameter_m: float) -> float:
    """Inner volume of a round tube.

    >>> round(tube_volume_m3(12.0, 1.2e-3) * 1e9, 1)   # the paper's 12 m × 1.2 mm ID, mm³
    13571.7
    """
    length = _positive("tube length (m)", length_m)
    d = _positive("tube inner diameter (m)", inner_diameter_m)
    return math.pi * d * d / 4.0 * length


def loss_factor(v_cavity_m3: float, v_tube_m3: float, v_dead_m3: float = 0.0) -> float:
    """The paper's "pressure-loss factor" V_total / V_cavity (dimensionless).

    A volume change δV of the cavity alone would give ΔP ≈ P0·δV/V_cavity; with the tube the same
    δV is shared by V_total, so the transducer reads that pressure divided by this factor.

    >>> round(loss_factor(486e-9, tube_volume_m3(12.0, 1.2e-3)), 1)
    28.9
    """
    vc = _positive("cavity volume (m³)", v_cavity_m3)
    return (vc + float(v_tube_m3) + float(v_dead_m3)) / vc


def boyle_dV(dp_Pa, v_total_m3, p0_Pa: float) -> np.ndarray:
    """Cavity volume change from the gauge pressure change, isothermal Boyle over cavity + tube.

    ΔV = V_T · (P0 / (P0 + ΔP) − 1); ``p0_Pa`` is the absolute ambient pressure at tare.
    Compressing the cavity (ΔV < 0) raises the pressure.

    >>> round(float(boyle_dV(1000.0, 14_058e-9, 101_325.0) * 1e9), 2)   # +1 kPa → mm³
    -137.39
    """
    p0 = _positive("P0 (Pa)", p0_Pa)
    dp = _finite("dp (Pa)", dp_Pa)
    vt = _finite("V_total (m³)", v_total_m3)
    if np.any(p0 + dp <= 0):
        raise UserError(f"dp (Pa): absolute pressure P0 + dp must stay positive (P0 = {p0:g} Pa)")
    return vt * (p0 / (p0 + dp) - 1.0)


def boyle_dp(dV_m3, v_total_m3, p0_Pa: float) -> np.ndarray:
    """Inverse of :func:`boyle_dV`: gauge pressure change for a cavity volume change.

    >>> round(float(boyle_dp(boyle_dV(250.0, 14e-6, 1e5), 14e-6, 1e5)), 9)
    250.0
    """
    p0 = _positive("P0 (Pa)", p0_Pa)
    dv = _finite("dV (m³)", dV_m3)
    vt = _finite("V_total (m³)", v_total_m3)
    if np.any(vt + dv <= 0):
        raise UserError("dV (m³): the gas volume V_total + dV must stay positive")
    return p0 * (vt / (vt + dv) - 1.0)


def thermal_dp_per_K(p0_Pa: float = 101_325.0, temperature_K: float = ROOM_TEMPERATURE_K) -> float:
    """Pressure change of a closed, rigid gas volume per kelvin: dP/dT = P/T (Pa/K).

    >>> round(thermal_dp_per_K())     # ≈ 340 Pa per kelvin at room conditions
    346
    """
    return _positive("P0 (Pa)", p0_Pa) / _positive("temperature (K)", temperature_K)


def poiseuille_resistance(length_m: float, inner_diameter_m: float,
                          viscosity_Pa_s: float = AIR_VISCOSITY_PA_S) -> float:
    """Laminar (Hagen–Poiseuille) flow resistance R = 128 μ L / (π d⁴), Pa·s/m³.

    >>> f"{poiseuille_resistance(12.0, 1.2e-3):.3g}"
    '4.27e+09'
    """
    length = _positive("tube length (m)", length_m)
    d = _positive("tube inner diameter (m)", inner_diameter_m)
    return 128.0 * _positive("viscosity (Pa·s)", viscosity_Pa_s) * length / (math.pi * d**4)


def tube_time_constant_s(length_m: float, inner_diameter_m: float, v_cavity_m3: float,
                         p0_Pa: float = 101_325.0, v_dead_m3: float = 0.0,
                         viscosity_Pa_s: float = AIR_VISCOSITY_PA_S,
                         method: str = "elmore") -> float:
    """First-order time constant of the pressure seen at the transducer end of the tube.

    The tube is a distributed RC line (resistance R = 128 μL/(πd⁴), isothermal capacitance
    C_t = V_tube/P0); the cavity (C_c = V_cavity/P0) is at the driven end, the transducer's dead
    volume (C_d) at the far end. ``method="elmore"`` (default) returns the mean delay (first
    moment) of the transducer's step response, the time constant of the first-order model with the
    same delay::

        τ = R · [ C_t/2 + C_d − (C_d² + C_t·C_d + C_t²/3) / (C_c + C_t + C_d) ]

    ``method="lumped"`` returns R·(C_c + C_t + C_d), the crude single-RC bound (too slow).
    For the paper's 12 m × 1.2 mm tube: 0.10 s (Elmore) and 0.59 s (lumped).

    >>> round(tube_time_constant_s(12.0, 1.2e-3, 486e-9), 3)
    0.102
    >>> round(tube_time_constant_s(12.0, 1.2e-3, 486e-9, method="lumped"), 2)
    0.59
    """
    p0 = _positive("P0 (Pa)", p0_Pa)
    r = poiseuille_resistance(length_m, inner_diameter_m, viscosity_Pa_s)
    ct = tube_volume_m3(length_m, inner_diameter_m) / p0
    cc = _positive("cavity volume (m³)", v_cavity_m3) / p0
    cd = float(v_dead_m3) / p0
    if cd < 0:
        raise UserError("dead volume (m³) must be ≥ 0")
    total = cc + ct + cd
    if method == "lumped":
        return r * total
    if method != "elmore":
        raise UserError(f"method: expected 'elmore' or 'lumped', got {method!r}")
    return r * (ct / 2.0 + cd - (cd * cd + ct * cd + ct * ct / 3.0) / total)


def lag_alpha(dt_s: float, tau_s: float) -> float:
    """Smoothing factor of the exact discretisation of a first-order lag: 1 − exp(−dt/τ).

    >>> round(lag_alpha(0.052, 0.102), 3)
    0.399
    """
    dt = _positive("dt (s)", dt_s)
    tau = float(tau_s)
    if not math.isfinite(tau) or tau < 0:
        raise UserError(f"tau (s) must be ≥ 0, got {tau_s!r}")
    return 1.0 if tau == 0 else 1.0 - math.exp(-dt / tau)


def first_order_lag(x, dt_s: float, tau_s: float, y0=None) -> np.ndarray:
    """Filter a sampled signal (samples along axis 0) through a first-order lag.

    y[k] = y[k−1] + α·(x[k] − y[k−1]), α = :func:`lag_alpha`; exact for a signal held constant
    over each sample (zero-order hold). ``y0`` is the state before the first sample (default
    ``x[0]``, i.e. starting at rest). Returns a new array; use it in the virtual phantom to delay
    the pressures the transducers see.

    >>> y = first_order_lag(np.ones(3), dt_s=0.1, tau_s=0.1, y0=0.0)
    >>> np.round(y, 3).tolist()
    [0.632, 0.865, 0.95]
    """
    xa = _finite("x", x)
    a = lag_alpha(dt_s, tau_s)
    y = np.empty_like(xa)
    prev = xa[0] if y0 is None else np.broadcast_to(np.asarray(y0, float), xa.shape[1:])
    for k in range(xa.shape[0]):
        prev = prev + a * (xa[k] - prev)
        y[k] = prev
    return y


@dataclass(frozen=True)
class DriftReport:
    """Slow trend of the arm pressures over a window.

    ``slope_Pa_per_s`` per arm (robust: difference of the medians of the window's first and last
    thirds), ``common_Pa_per_s`` their median, ``equivalent_K_per_min`` the temperature drift
    of a closed volume that would explain it, ``drifting`` the verdict and ``reason`` why.
    """

    slope_Pa_per_s: np.ndarray
    common_Pa_per_s: float
    equivalent_K_per_min: float
    drifting: bool
    reason: str


def detect_drift(t_s, dp_Pa, window_s: float = 60.0, max_slope_Pa_per_s: float = 0.6,
                 p0_Pa: float = 101_325.0) -> DriftReport:
    """Detect a slow common-mode trend (temperature) in the last ``window_s`` of arm pressures.

    A push moves arms in different directions and comes back; a temperature change moves all
    closed volumes the same way by P0/T ≈ 346 Pa/K. The default threshold 0.6 Pa/s ≈ 0.1 K/min.
    Drifting means: the median slope exceeds the threshold and every arm trends the same way.

    >>> t = np.arange(0, 60, 0.05)
    >>> ramp = (346 / 60) * t                     # +1 K per minute on every arm
    >>> detect_drift(t, np.stack([ramp] * 4, axis=1)).drifting
    True
    """
    t = _finite("t (s)", t_s)
    dp = _finite("dp (Pa)", dp_Pa)
    if dp.ndim != 2 or dp.shape[0] != t.shape[0]:
        raise UserError(f"dp (Pa): expected shape (n, k) with n = len(t) = {t.shape[0]}, got {dp.shape}")
    sel = t >= t[-1] - _positive("window (s)", window_s)
    t, dp = t[sel], dp[sel]
    if t.shape[0] < 6 or t[-1] - t[0] <= 0:
        raise UserError(f"drift window: need ≥ 6 samples spanning time, got {t.shape[0]}")
    third = t.shape[0] // 3
    dt = float(np.median(t[-third:]) - np.median(t[:third]))
    slope = (np.median(dp[-third:], axis=0) - np.median(dp[:third], axis=0)) / dt
    common = float(np.median(slope))
    k_per_min = common / thermal_dp_per_K(p0_Pa) * 60.0
    same_sign = bool(np.all(np.sign(slope) == np.sign(common))) and common != 0
    drifting = abs(common) > max_slope_Pa_per_s and same_sign
    if drifting:
        reason = f"common trend {common:+.2f} Pa/s on every arm (≈ {k_per_min:+.2f} K/min); re-tare"
    elif abs(common) > max_slope_Pa_per_s:
        reason = f"trend {common:+.2f} Pa/s but arms disagree in sign (a load, not temperature)"
    else:
        reason = f"trend {common:+.2f} Pa/s within ±{max_slope_Pa_per_s:g} Pa/s"
    return DriftReport(slope, common, k_per_min, drifting, reason)
