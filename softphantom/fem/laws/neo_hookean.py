"""Compressible neo-Hookean: W = μ/2 (I₁ − 3) − μ ln J + λ/2 (ln J)², I₁ = tr FᵀF, J = det F, with
μ, λ the Lamé constants of (E, ν); P = μ F + (λ ln J − μ) F⁻ᵀ. Parameter row (μ, λ, 0, 0) Pa."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from softphantom.fem.laws.base import Isotropic, det_inv, point_function


@point_function
def point(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    mu, lam = prm[e, 0], prm[e, 1]
    Fi = s0
    J = det_inv(F, Fi)
    lnJ = math.log(J)
    I1 = 0.0
    for i in range(3):
        for j in range(3):
            I1 += F[i, j] * F[i, j]
    if need >= 1:
        c = lam * lnJ - mu
        for i in range(3):
            for j in range(3):
                P[i, j] = mu * F[i, j] + c * Fi[j, i]
    if need >= 2:
        a = mu - lam * lnJ
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    for l in range(3):
                        d = a * Fi[j, k] * Fi[l, i] + lam * Fi[j, i] * Fi[l, k]
                        if i == k and j == l:
                            d += mu
                        D[3 * i + j, 3 * k + l] = d
    return 0.5 * mu * (I1 - 3.0) - mu * lnJ + 0.5 * lam * lnJ * lnJ


@dataclass(frozen=True)
class NeoHookean(Isotropic):
    """Compressible neo-Hookean: W = μ/2 (I₁ − 3) − μ ln J + λ/2 (ln J)², with μ, λ the Lamé
    constants of (E, ν); P = μ F + (λ ln J − μ) F⁻ᵀ.

    >>> NeoHookean(E_Pa=142.3e3, nu=0.5)
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: nu = 0.5 must be in (-1, 0.5) (compressible)
    """

    name: ClassVar[str] = "neo-hookean"
    point = staticmethod(point)
