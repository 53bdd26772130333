"""Three-term Yeoh law, nearly incompressible: W = Σ_{i=1..3} C_i0 (Ī₁ − 3)^i + K/2 (J − 1)² with the
isochoric Ī₁ = J^(−2/3) tr(FᵀF) (the Abaqus/Altair form, D1 = 2/K). Parameter row (C10, C20, C30, K) Pa."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from softphantom.errors import UserError
from softphantom.fem.laws.base import Law, Ratio, check, det_inv, point_function


@point_function
def point(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    c1, c2, c3, K = prm[e, 0], prm[e, 1], prm[e, 2], prm[e, 3]
    Fi, G = s0, s1
    J = det_inv(F, Fi)
    I1 = 0.0
    for i in range(3):
        for j in range(3):
            I1 += F[i, j] * F[i, j]
    g = J ** (-2.0 / 3.0)
    b = g * I1  # Ī₁
    x = b - 3.0
    W = c1 * x + c2 * x * x + c3 * x * x * x + 0.5 * K * (J - 1.0) ** 2
    if need >= 1:
        w1 = c1 + 2.0 * c2 * x + 3.0 * c3 * x * x  # dW/dĪ₁
        kv = K * (J - 1.0) * J  # (dU/dJ) J
        for i in range(3):
            for j in range(3):
                G[i, j] = 2.0 * g * F[i, j] - (2.0 / 3.0) * b * Fi[j, i]  # dĪ₁/dF
                P[i, j] = w1 * G[i, j] + kv * Fi[j, i]
    if need >= 2:
        w11 = 2.0 * c2 + 6.0 * c3 * x
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    for l in range(3):
                        # d²Ī₁/dF² and d(J F⁻ᵀ)/dF
                        h = (
                            -(4.0 / 3.0) * g * F[i, j] * Fi[l, k]
                            - (2.0 / 3.0) * G[k, l] * Fi[j, i]
                            + (2.0 / 3.0) * b * Fi[j, k] * Fi[l, i]
                        )
                        if i == k and j == l:
                            h += 2.0 * g
                        d = w11 * G[i, j] * G[k, l] + w1 * h
                        d += K * J * J * Fi[j, i] * Fi[l, k]
                        d += K * (J - 1.0) * J * (Fi[l, k] * Fi[j, i] - Fi[j, k] * Fi[l, i])
                        D[3 * i + j, 3 * k + l] = d
    return W




@dataclass(frozen=True)
class Yeoh(Law):
    """Three-term Yeoh law, nearly incompressible: W = Σ C_i0 (Ī₁ − 3)^i + K/2 (J − 1)² with the
    isochoric Ī₁ = J^(−2/3) tr(FᵀF) (the Abaqus/Altair form, D1 = 2/K). Small-strain shear modulus
    μ = 2 C10; the bulk modulus K = 2μ(1+ν) / (3(1−2ν)) comes from ``nu``.

    Valid parameters: C10 > 0 and dW/dĪ₁ = C10 + 2 C20 x + 3 C30 x² > 0 for every x = Ī₁ − 3 >= 0
    (a stable law in every deformation), ν in (−1, 0.5). Its shape C20/C10, C30/C10 is what a
    calibration may fit (:attr:`ratios`; silicone fits span |C20/C10| up to a few hundredths and
    C30/C10 up to ~0.01, the Ecoflex 00-50 preset −0.012, 0.0014: the priors' spreads).

    >>> y = Yeoh(C10_Pa=17.0e3, C20_Pa=-0.2e3, C30_Pa=0.023e3, nu=0.45)
    >>> round(y.mu_Pa), round(y.E_Pa)
    (34000, 98600)
    """

    C10_Pa: float
    C20_Pa: float = 0.0
    C30_Pa: float = 0.0
    nu: float = 0.45
    density_kg_m3: float = 1000.0

    name: ClassVar[str] = "yeoh"
    point = staticmethod(point)
    ratios: ClassVar[tuple[Ratio, ...]] = (Ratio("C20_C10", "C20_Pa", "C10_Pa", 1, 0, 0.05),
                                           Ratio("C30_C10", "C30_Pa", "C10_Pa", 2, 0, 0.01))

    def __post_init__(self) -> None:
        check(math.isfinite(self.C10_Pa) and self.C10_Pa > 0, "C10_Pa", self.C10_Pa, "> 0")
        for f in ("C20_Pa", "C30_Pa"):
            check(math.isfinite(getattr(self, f)), f, getattr(self, f), "finite")
        check(-1.0 < self.nu < 0.5, "nu", self.nu, "in (-1, 0.5) (compressible)")
        check(self.density_kg_m3 >= 0, "density_kg_m3", self.density_kg_m3, ">= 0")
        c1, c2, c3 = self.C10_Pa, self.C20_Pa, self.C30_Pa
        # min over x >= 0 of c1 + 2 c2 x + 3 c3 x²: negative somewhere iff c3 < 0, or c2 < 0 with
        # the vertex value c1 − c2²/(3 c3) <= 0
        unstable = c3 < 0 or (c3 == 0 and c2 < 0) or (c3 > 0 and c2 < 0 and c1 - c2 * c2 / (3 * c3) <= 0)
        if unstable:
            raise UserError(
                f"C20_Pa = {c2:.6g} must keep dW/dI1 = C10 + 2 C20 x + 3 C30 x² > 0 for all x >= 0 "
                f"(with C30_Pa = {c3:.6g}; an unstable law otherwise)"
            )

    @property
    def mu_Pa(self) -> float:
        return 2.0 * self.C10_Pa

    @property
    def bulk_Pa(self) -> float:
        return 2.0 * self.mu_Pa * (1.0 + self.nu) / (3.0 * (1.0 - 2.0 * self.nu))

    @property
    def lambda_Pa(self) -> float:
        return self.bulk_Pa - 2.0 * self.mu_Pa / 3.0

    @property
    def E_Pa(self) -> float:
        return 2.0 * self.mu_Pa * (1.0 + self.nu)

    def params(self) -> np.ndarray:
        """(C10, C20, C30, K) Pa."""
        return np.array([self.C10_Pa, self.C20_Pa, self.C30_Pa, self.bulk_Pa])

    @classmethod
    def from_small_strain(cls, E_Pa: float, nu: float, density_kg_m3: float) -> Yeoh:
        """C10 = μ/2, C20 = C30 = 0: the decoupled neo-Hookean form."""
        return cls(C10_Pa=E_Pa / (4.0 * (1.0 + nu)), nu=nu, density_kg_m3=density_kg_m3)

    @classmethod
    def feasible_ratios(cls, values, free) -> tuple[float, ...]:
        """Into the stable set (dW/dĪ₁ > 0 for every Ī₁ ≥ 3): C30/C10 ≥ 0, and above (C20/C10)²/3
        where C20 < 0 (C30 lifted if free, else C20 bounded from below). From the boundary — the
        small-strain form C20 = C30 = 0, where any step with C20 < 0 and C30 ≤ 0 is unstable — a
        step is projected back rather than rejected: rejecting it left a fit at its start whenever
        the data did not ask for C30 > 0.

        >>> Yeoh.feasible_ratios((-0.03, 0.0), (True, True))[1] > 0.03 ** 2 / 3
        True
        """
        t2, t3 = (float(v) for v in values)
        if free[1]:
            t3 = max(t3, (t2 * t2 / 3.0) * (1.0 + 1e-3) + 1e-12 if t2 < 0 else 0.0)
        elif free[0]:
            t2 = max(t2, -math.sqrt(3.0 * t3 / (1.0 + 1e-3)) if t3 > 0 else 0.0)
        return (t2, t3)
