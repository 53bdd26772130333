"""The tube of one sensing arm as the distributed RC line it is (docs/sensing.md §6).

The gas column of a tube of length L and bore d is a uniform RC line: resistance R = 128·μ·L/(π·d⁴)
(Hagen–Poiseuille), capacitance C_t = V_tube/P0 (isothermal), with the cavity C_c at the driven end
and the transducer's dead volume C_d at the far end. A cavity volume change puts gas at x = 0; the
equilibrium pressure of the whole arm, ``p_eq`` (what Boyle gives for the cavity's ΔV over V_T),
reaches the transducer through

    H(s) = p_d / p_eq = C_tot / [ (C_c + C_d)·cosh γ + (C_t + s·R·C_c·C_d)·sinh γ / γ ],  γ² = s·R·C_t

(the line's two-port closed by C_d, driven by a flow source beside C_c; C_tot = C_c + C_t + C_d).
Its denominator is an entire function of s with real negative zeros only, so the line is exactly an
infinite cascade of first-order lags, H = Π 1/(1 + s·τ_n), whose time constants sum to the Elmore
delay (:func:`~softphantom.sensing.pneumatics.tube_time_constant_s`). For the paper's tube and a
486 mm³ cavity: τ_1 = 62 ms, τ_2 = 15.5 ms, τ_3 = 6.9 ms, …, Σ = 102 ms.

:class:`TubeLine` holds a line; :meth:`TubeLine.stages` gives the first time constants of the
cascade (the estimator's lag compensation models the tube by a few of them and one stage with the
rest of the delay); :meth:`TubeLine.ladder_response` simulates the line as a ladder of RC segments
(the virtual phantom's transducer pressures), exact for an input linear between samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError
from softphantom.sensing.pneumatics import AIR_VISCOSITY_PA_S, poiseuille_resistance, tube_volume_m3

LADDER_SEGMENTS = 48
"""RC segments of the virtual phantom's tube: its step response is within 0.1 % of the
400-segment ladder's (tests/test_tube.py)."""

TAU_RANGE_FACTOR = 2.0
"""A tube time constant is physical for a stated tube between R·C_t/6 (the line alone) and
R·(C_c + C_t + C_d) (the lumped bound), widened by this factor either way (a measured tube is not
its nominal one)."""


@dataclass(frozen=True)
class TubeLine:
    """One arm's pneumatic line (SI): ``r`` Pa·s/m³ total resistance, ``c_cavity``, ``c_tube``,
    ``c_dead`` m³/Pa isothermal capacitances (V/P0).

    >>> line = TubeLine.of(12.0, 1.2e-3, 486e-9)
    >>> round(line.elmore_s, 3), [round(float(t) * 1e3, 1) for t in line.stages(3)]
    (0.102, [62.1, 15.5, 6.9])
    """

    r: float
    c_cavity: float
    c_tube: float
    c_dead: float = 0.0

    @classmethod
    def of(cls, length_m: float, inner_diameter_m: float, v_cavity_m3: float, p0_Pa: float = 101_325.0,
           v_dead_m3: float = 0.0, viscosity_Pa_s: float = AIR_VISCOSITY_PA_S) -> "TubeLine":
        """The line of a tube ``length_m`` × ``inner_diameter_m`` between a cavity and a transducer."""
        if not (math.isfinite(p0_Pa) and p0_Pa > 0):
            raise UserError(f"P0 (Pa) must be a positive number, got {p0_Pa!r}")
        if not (math.isfinite(v_cavity_m3) and v_cavity_m3 > 0):
            raise UserError(f"cavity volume (m³) must be a positive number, got {v_cavity_m3!r}")
        if not (math.isfinite(v_dead_m3) and v_dead_m3 >= 0):
            raise UserError(f"dead volume (m³) must be ≥ 0, got {v_dead_m3!r}")
        return cls(poiseuille_resistance(length_m, inner_diameter_m, viscosity_Pa_s), v_cavity_m3 / p0_Pa,
                   tube_volume_m3(length_m, inner_diameter_m) / p0_Pa, v_dead_m3 / p0_Pa)

    @property
    def c_total(self) -> float:
        return self.c_cavity + self.c_tube + self.c_dead

    @property
    def elmore_s(self) -> float:
        """The mean delay (first moment of the step response) = Σ of the cascade's time constants."""
        ct, cd = self.c_tube, self.c_dead
        return self.r * (ct / 2.0 + cd - (cd * cd + ct * cd + ct * ct / 3.0) / self.c_total)

    @property
    def tau_range_s(self) -> tuple[float, float]:
        """(low, high): the time constants this tube can physically have (:data:`TAU_RANGE_FACTOR`)."""
        return (self.r * self.c_tube / 6.0 / TAU_RANGE_FACTOR, self.r * self.c_total * TAU_RANGE_FACTOR)

    def transfer(self, s) -> np.ndarray:
        """H(s) = p_transducer / p_eq at complex frequencies ``s`` (rad/s; closed form above)."""
        s = np.asarray(s, complex)
        g = np.sqrt(s * self.r * self.c_tube)
        small = np.abs(g) < 1e-6
        gs = np.where(small, 1.0, g)
        shc = np.where(small, 1.0 + g * g / 6.0, np.sinh(gs) / gs)
        den = (self.c_cavity + self.c_dead) * np.cosh(g) + (self.c_tube + s * self.r * self.c_cavity * self.c_dead) * shc
        return self.c_total / den

    def stages(self, n: int) -> np.ndarray:
        """The ``n`` slowest time constants (s) of the cascade H = Π 1/(1 + s·τ_k): the zeros of the
        denominator, s = −θ²/(R·C_t), where (a + b)·θ·cos θ + (1 − a·b·θ²)·sin θ = 0,
        a = C_c/C_t, b = C_d/C_t; one root in each interval between the zeros of sin and cos."""
        from scipy.optimize import brentq

        a, b = self.c_cavity / self.c_tube, self.c_dead / self.c_tube

        def f(th: float) -> float:
            return (a + b) * th * math.cos(th) + (1.0 - a * b * th * th) * math.sin(th)

        # the roots interleave with the grid of multiples of π/2: bracket on a fine grid
        roots: list[float] = []
        hi = 0.0
        step = math.pi / 64.0
        lo_val = f(1e-9)
        x = 1e-9
        while len(roots) < n:
            hi = x + step
            v = f(hi)
            if lo_val == 0.0 or (lo_val < 0) != (v < 0):
                roots.append(brentq(f, x, hi, xtol=1e-14))
            x, lo_val = hi, v
        th = np.array(roots)
        return self.r * self.c_tube / th**2

    def reduced(self, n: int) -> np.ndarray:
        """A cascade of ``n`` + 1 first-order lags with the line's Elmore delay: its ``n`` slowest
        stages and one with the rest of the delay (the faster stages' sum)."""
        tau = self.stages(n)
        return np.append(tau, max(self.elmore_s - float(tau.sum()), 0.0))

    # ------------------------------------------------------------------ ladder (simulation)
    def ladder(self, n_segments: int = LADDER_SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
        """(C (n+1,), G (n+1, n+1)): node capacitances and conductance Laplacian of the line cut in
        ``n_segments`` equal RC segments (half a segment's capacitance at each end, plus the
        cavity's at node 0 and the dead volume's at node n)."""
        n = int(n_segments)
        if n < 1:
            raise UserError(f"ladder segments: need ≥ 1, got {n_segments!r}")
        cseg = self.c_tube / n
        cap = np.full(n + 1, cseg)
        cap[0] = cseg / 2.0 + self.c_cavity
        cap[-1] = cseg / 2.0 + self.c_dead
        g = n / self.r
        lap = np.zeros((n + 1, n + 1))
        i = np.arange(n)
        lap[i, i] += g
        lap[i + 1, i + 1] += g
        lap[i, i + 1] -= g
        lap[i + 1, i] -= g
        return cap, lap

    def ladder_response(self, p_eq, dt_s: float, n_segments: int = LADDER_SEGMENTS) -> np.ndarray:
        """The transducer-end pressure of the ladder for the equilibrium pressure ``p_eq`` sampled
        every ``dt_s`` (axis 0; the line at rest at ``p_eq[0]`` before the first sample), exact for
        ``p_eq`` linear between samples: the cavity's gas flow C_tot·dp_eq/dt is constant over each
        step. Modal: C⁻½·G·C⁻½ = V·Λ·Vᵀ, each mode an exactly discretised first-order system."""
        from scipy.signal import lfilter

        x = np.asarray(p_eq, float)
        if x.ndim != 1:
            raise UserError(f"p_eq: expected one signal, got shape {x.shape}")
        if not np.all(np.isfinite(x)):
            raise UserError("p_eq: not finite")
        dt = float(dt_s)
        if not (math.isfinite(dt) and dt > 0):
            raise UserError(f"dt (s) must be positive, got {dt_s!r}")
        cap, lap = self.ladder(n_segments)
        ih = 1.0 / np.sqrt(cap)
        lam, v = np.linalg.eigh(ih[:, None] * lap * ih[None, :])
        lam = np.maximum(lam, 0.0)
        # flow into node 0 (constant over each step): i_k = C_tot·(p_eq[k+1] − p_eq[k])/dt
        flow = np.diff(x) * (self.c_total / dt)
        b = v[0, :] * ih[0]                  # modal input of node 0
        c = v[-1, :] * ih[-1]                # far-end node of the modes
        out = x.copy()                       # the charge mode: the equilibrium pressure itself
        u = np.append(flow, 0.0)
        for k in range(len(lam)):
            if lam[k] * dt < 1e-12:
                continue
            a = math.exp(-lam[k] * dt)
            # η[j+1] = a·η[j] + (1 − a)/λ·b·flow[j], η[0] = 0 (at rest)
            out += c[k] * lfilter([0.0, (1.0 - a) / lam[k] * b[k]], [1.0, -a], u)
        return out
