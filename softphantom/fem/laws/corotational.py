"""The co-rotational Hooke law (the paper's): W = μ‖S − I‖² + λ/2 tr²(S − I) with F = R S (polar
decomposition), P = R σ(S), σ = 2μ(S − I) + λ tr(S − I) I. Parameter row (μ, λ, 0, 0) Pa.

The polar decomposition is Higham's scaled Newton iteration X ← (γX + X⁻ᵀ/γ)/2; ``need == 3`` asks
for the classic approximate tangent R K0 Rᵀ instead of the consistent one. The batched numpy
reference of the same law on linear tets is :mod:`softphantom.fem.corotational`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from softphantom.fem._numba import njit
from softphantom.fem.laws.base import Isotropic, point_function


@point_function
def polar(F, R, S, X, Y):
    """Proper rotation R and symmetric S of F = R S (det F > 0) by scaled Newton (Higham 1986).

    X, Y: (3,3) scratch."""
    for i in range(3):
        for j in range(3):
            X[i, j] = F[i, j]
    scaled = True
    for _ in range(60):
        # cofactor matrix C: X⁻ᵀ = C / det X
        c00 = X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]
        c01 = X[1, 2] * X[2, 0] - X[1, 0] * X[2, 2]
        c02 = X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]
        c10 = X[0, 2] * X[2, 1] - X[0, 1] * X[2, 2]
        c11 = X[0, 0] * X[2, 2] - X[0, 2] * X[2, 0]
        c12 = X[0, 1] * X[2, 0] - X[0, 0] * X[2, 1]
        c20 = X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1]
        c21 = X[0, 2] * X[1, 0] - X[0, 0] * X[1, 2]
        c22 = X[0, 0] * X[1, 1] - X[0, 1] * X[1, 0]
        det = X[0, 0] * c00 + X[0, 1] * c01 + X[0, 2] * c02
        g = 1.0
        if scaled:
            g = abs(det) ** (-1.0 / 3.0)
        a = 0.5 * g
        b = 0.5 / (g * det)
        Y[0, 0] = a * X[0, 0] + b * c00
        Y[0, 1] = a * X[0, 1] + b * c01
        Y[0, 2] = a * X[0, 2] + b * c02
        Y[1, 0] = a * X[1, 0] + b * c10
        Y[1, 1] = a * X[1, 1] + b * c11
        Y[1, 2] = a * X[1, 2] + b * c12
        Y[2, 0] = a * X[2, 0] + b * c20
        Y[2, 1] = a * X[2, 1] + b * c21
        Y[2, 2] = a * X[2, 2] + b * c22
        d = 0.0
        for i in range(3):
            for j in range(3):
                d = max(d, abs(Y[i, j] - X[i, j]))
                X[i, j] = Y[i, j]
        if d < 1e-3:
            scaled = False  # near convergence: plain Newton (scaling would only add round-off)
        if d < 1e-11:
            break  # quadratic convergence: the error is now far below round-off
    for i in range(3):
        for j in range(3):
            R[i, j] = X[i, j]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += R[k, i] * F[k, j]
            Y[i, j] = s
    for i in range(3):
        for j in range(3):
            S[i, j] = 0.5 * (Y[i, j] + Y[j, i])


@point_function
def _stress(S, mu, lam, sig):
    tr = (S[0, 0] - 1.0) + (S[1, 1] - 1.0) + (S[2, 2] - 1.0)
    for i in range(3):
        for j in range(3):
            E = S[i, j] - (1.0 if i == j else 0.0)
            sig[i, j] = 2.0 * mu * E + (lam * tr if i == j else 0.0)


@njit(fastmath=False, nogil=True)
def _dP_dF(R, S, mu, lam, consistent, D, M, W, dS, sig, Ginv):
    """D (9,9) = dP/dF of P = R σ(S) at F = R S, rows and columns row-major over (i,j); the same
    formulas as the numpy reference ``corotational._dP_dF``."""
    if consistent:
        _stress(S, mu, lam, sig)
        trS = S[0, 0] + S[1, 1] + S[2, 2]
        g00 = trS - S[0, 0]
        g01 = -S[0, 1]
        g02 = -S[0, 2]
        g10 = -S[1, 0]
        g11 = trS - S[1, 1]
        g12 = -S[1, 2]
        g20 = -S[2, 0]
        g21 = -S[2, 1]
        g22 = trS - S[2, 2]
        c00 = g11 * g22 - g12 * g21
        c01 = g12 * g20 - g10 * g22
        c02 = g10 * g21 - g11 * g20
        c10 = g02 * g21 - g01 * g22
        c11 = g00 * g22 - g02 * g20
        c12 = g01 * g20 - g00 * g21
        c20 = g01 * g12 - g02 * g11
        c21 = g02 * g10 - g00 * g12
        c22 = g00 * g11 - g01 * g10
        idet = 1.0 / (g00 * c00 + g01 * c01 + g02 * c02)
        # inverse = adjugate / det = cofactorᵀ / det
        Ginv[0, 0] = c00 * idet
        Ginv[0, 1] = c10 * idet
        Ginv[0, 2] = c20 * idet
        Ginv[1, 0] = c01 * idet
        Ginv[1, 1] = c11 * idet
        Ginv[1, 2] = c21 * idet
        Ginv[2, 0] = c02 * idet
        Ginv[2, 1] = c12 * idet
        Ginv[2, 2] = c22 * idet
    for k in range(3):
        for l in range(3):
            # M = Rᵀ E_kl: M_ij = R_ki δ_lj
            for i in range(3):
                for j in range(3):
                    M[i, j] = R[k, i] if j == l else 0.0
            if consistent:
                a0 = M[2, 1] - M[1, 2]
                a1 = M[0, 2] - M[2, 0]
                a2 = M[1, 0] - M[0, 1]
                w0 = Ginv[0, 0] * a0 + Ginv[0, 1] * a1 + Ginv[0, 2] * a2
                w1 = Ginv[1, 0] * a0 + Ginv[1, 1] * a1 + Ginv[1, 2] * a2
                w2 = Ginv[2, 0] * a0 + Ginv[2, 1] * a1 + Ginv[2, 2] * a2
                W[0, 0] = 0.0
                W[1, 1] = 0.0
                W[2, 2] = 0.0
                W[0, 1] = -w2
                W[0, 2] = w1
                W[1, 2] = -w0
                W[1, 0] = w2
                W[2, 0] = -w1
                W[2, 1] = w0
                for i in range(3):
                    for j in range(3):
                        dS[i, j] = M[i, j] - (
                            W[i, 0] * S[0, j] + W[i, 1] * S[1, j] + W[i, 2] * S[2, j]
                        )
            else:
                for i in range(3):
                    for j in range(3):
                        dS[i, j] = 0.5 * (M[i, j] + M[j, i])
            trd = dS[0, 0] + dS[1, 1] + dS[2, 2]
            # T = inner + dsig, inner = W σ (consistent only); reuse M as T
            for i in range(3):
                for j in range(3):
                    t = 2.0 * mu * dS[i, j] + (lam * trd if i == j else 0.0)
                    if consistent:
                        t += W[i, 0] * sig[0, j] + W[i, 1] * sig[1, j] + W[i, 2] * sig[2, j]
                    M[i, j] = t
            kl = 3 * k + l
            for i in range(3):
                for j in range(3):
                    D[3 * i + j, kl] = R[i, 0] * M[0, j] + R[i, 1] * M[1, j] + R[i, 2] * M[2, j]



@point_function
def point(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    mu, lam = prm[e, 0], prm[e, 1]
    R, S, X, Y = s0, s1, s2, s3
    polar(F, R, S, X, Y)
    tr = (S[0, 0] - 1.0) + (S[1, 1] - 1.0) + (S[2, 2] - 1.0)
    ee = 0.0
    for i in range(3):
        for j in range(3):
            E = S[i, j] - (1.0 if i == j else 0.0)
            ee += E * E
    if need >= 1:
        sig = s4
        _stress(S, mu, lam, sig)
        for i in range(3):
            for j in range(3):
                P[i, j] = R[i, 0] * sig[0, j] + R[i, 1] * sig[1, j] + R[i, 2] * sig[2, j]
    if need >= 2:
        _dP_dF(R, S, mu, lam, need == 2, D, s5, s6, s7, s8, s9)
    return mu * ee + 0.5 * lam * tr * tr


@dataclass(frozen=True)
class Corotational(Isotropic):
    """Co-rotational Hooke law (the paper's): W = μ‖S − I‖² + λ/2 tr²(S − I), F = R S.

    >>> m = Corotational(E_Pa=3.0e3, nu=0.25, density_kg_m3=1000.0)
    >>> round(m.mu_Pa, 6), round(m.lambda_Pa, 6), m.name
    (1200.0, 1200.0, 'corotational')
    """

    name: ClassVar[str] = "corotational"
    point = staticmethod(point)
