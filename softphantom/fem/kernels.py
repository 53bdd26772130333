"""numba kernels of the FEM hot paths: the material laws' point functions and the element loops
(internal force, strain energy, tangent written straight into the CSR data array).

**One point function per law**, ``law_point(law_id, prm, e, F, P, D, need, *scratch) -> W``: at one
quadrature point, from the deformation gradient F and row ``e`` of the parameter array ``prm``, the strain
energy density W (J/m³), the first Piola–Kirchhoff stress P (``need >= 1``) and the tangent
D = dP/dF (``need >= 2``; rows and columns row-major over (i, j): ``D[3i+j, 3k+l] = ∂P_ij/∂F_kl``).
The force, energy and tangent kernels all call it, so a law is written once. Laws (ids as in
:mod:`softphantom.fem.material`):

- 0 ``corotational``: W = μ‖S − I‖² + λ/2 tr²(S − I) with F = R S (polar decomposition by Higham's
  scaled Newton iteration X ← (γX + X⁻ᵀ/γ)/2), P = R σ(S); ``need == 3`` asks for the classic
  approximate tangent R K0 Rᵀ instead of the consistent one. prm = (μ, λ).
- 1 ``neo-hookean``: W = μ/2 (I₁ − 3) − μ ln J + λ/2 (ln J)²; P = μ F + (λ ln J − μ) F⁻ᵀ. prm = (μ, λ).
- 2 ``yeoh``: W = Σ_{i=1..3} C_i0 (Ī₁ − 3)^i + K/2 (J − 1)², Ī₁ = J^(−2/3) I₁. prm = (C10, C20, C30, K).

Elements: ``conn`` (M, n) node indices (n = 4 linear, 10 quadratic), ``dN`` (M, Q, n, 3) the rest
gradients ∇_X N_a at Q quadrature points, ``wq`` (M, Q) the quadrature weights times det J (m³).
F = Σ_a x_a ⊗ ∇N_a at each point.

Every kernel returns the number of quadrature points with det F <= 0 (or NaN), counted before any
output is touched; the caller raises :class:`~softphantom.fem.corotational.ElementInversionError`.
If numba is not importable, ``HAVE_NUMBA`` is False and the functions run as plain Python (slow,
same results); :mod:`softphantom.fem.corotational` then prefers its numpy path where it has one.

Compiled on first use and cached on disk (``cache=True``); serial (``parallel=False``) so results are
deterministic and bit-identical from run to run; ``nogil=True`` so the estimator's background
equilibrium thread does not hold up the foreground (numpy/scipy release the GIL too).
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a dependency; stay importable without it (numpy fallback)
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def deco(fn):
            return fn

        return deco


LAW_COROTATIONAL, LAW_NEO_HOOKEAN, LAW_YEOH = 0, 1, 2
N_PARAMS = 4  # columns of the per-element parameter array
N_WORK = 10  # (3,3) scratch matrices a law point function may use


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _polar(F, R, S, X, Y):
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


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _stress(S, mu, lam, sig):
    tr = (S[0, 0] - 1.0) + (S[1, 1] - 1.0) + (S[2, 2] - 1.0)
    for i in range(3):
        for j in range(3):
            E = S[i, j] - (1.0 if i == j else 0.0)
            sig[i, j] = 2.0 * mu * E + (lam * tr if i == j else 0.0)


@njit(cache=True, fastmath=False, nogil=True)
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


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _det_inv(F, Finv):
    """det F, and F⁻¹ into Finv (if det != 0)."""
    c00 = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    c01 = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    c02 = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    det = F[0, 0] * c00 + F[0, 1] * c01 + F[0, 2] * c02
    if det == 0.0:
        return det
    idet = 1.0 / det
    Finv[0, 0] = c00 * idet
    Finv[1, 0] = c01 * idet
    Finv[2, 0] = c02 * idet
    Finv[0, 1] = (F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]) * idet
    Finv[1, 1] = (F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]) * idet
    Finv[2, 1] = (F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]) * idet
    Finv[0, 2] = (F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]) * idet
    Finv[1, 2] = (F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]) * idet
    Finv[2, 2] = (F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]) * idet
    return det


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _corotational(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    mu, lam = prm[e, 0], prm[e, 1]
    R, S, X, Y = s0, s1, s2, s3
    _polar(F, R, S, X, Y)
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


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _neo_hookean(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    mu, lam = prm[e, 0], prm[e, 1]
    Fi = s0
    J = _det_inv(F, Fi)
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


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _yeoh(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    c1, c2, c3, K = prm[e, 0], prm[e, 1], prm[e, 2], prm[e, 3]
    Fi, G = s0, s1
    J = _det_inv(F, Fi)
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


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def law_point(law, prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9):
    """W (J/m³) of law ``law`` with the parameters of row ``e`` of ``prm`` at F (det F > 0);
    P (3,3) if ``need >= 1``; D (9,9) = dP/dF if ``need >= 2`` (``need == 3``: the law's
    approximate tangent, where it has one). ``s0``..``s9``: (3,3) scratch arrays
    (:func:`scratch`; passed one by one, inlined: no per-call tuple or view overhead). Add a law here and in :mod:`softphantom.fem.material`, nowhere else."""
    if law == LAW_COROTATIONAL:
        return _corotational(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
    if law == LAW_NEO_HOOKEAN:
        return _neo_hookean(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
    return _yeoh(prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def scratch():
    """The N_WORK (3,3) scratch arrays of a law point function, as a tuple (static indexing: no
    array views made per call)."""
    return (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)))


def point(law: int, prm, F, need: int = 2):
    """(W, P, D) of a law at one F, from Python (tests, closed forms): the same point function the
    element kernels call.

    >>> import numpy as np
    >>> W, P, D = point(LAW_NEO_HOOKEAN, np.array([1.0, 2.0, 0, 0]), np.eye(3))
    >>> W, float(abs(P).max()), D.shape
    (0.0, 0.0, (9, 9))
    """
    P = np.zeros((3, 3))
    D = np.zeros((9, 9))
    prm = np.pad(np.asarray(prm, float), (0, N_PARAMS - len(prm)))[None]
    W = law_point(int(law), prm, 0, np.ascontiguousarray(F, dtype=np.float64), P, D, int(need), *scratch())
    return float(W), P, D


@njit(cache=True, fastmath=False, nogil=True)
def _defgrad(x, conn, dN, e, q, F):
    """F = Σ_a x_a ⊗ ∇N_a of element e at quadrature point q into F (3,3); returns det F."""
    for i in range(3):
        for j in range(3):
            F[i, j] = 0.0
    for a in range(conn.shape[1]):
        n = conn[e, a]
        g0 = dN[e, q, a, 0]
        g1 = dN[e, q, a, 1]
        g2 = dN[e, q, a, 2]
        for i in range(3):
            xi = x[3 * n + i]
            F[i, 0] += xi * g0
            F[i, 1] += xi * g1
            F[i, 2] += xi * g2
    return (
        F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
        - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
        + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0])
    )


@njit(cache=True, fastmath=False, nogil=True)
def _count_inverted(x, conn, dN, F):
    """Quadrature points with det F <= 0 (or NaN); checked before any output is touched."""
    bad = 0
    for e in range(conn.shape[0]):
        for q in range(dN.shape[1]):
            if not _defgrad(x, conn, dN, e, q, F) > 0.0:
                bad += 1
    return bad


MODE_ENERGY, MODE_FORCE, MODE_STRESS = 0, 1, 2


@njit(cache=True, fastmath=False, nogil=True)
def point_loop_kernel(x, conn, dN, wq, law, prm, edofs, mode, force, stress):
    """One pass over every quadrature point: the strain energy Σ_e Σ_q w_q W(F) always, and
    (``mode`` MODE_FORCE) the internal force Σ_q w_q P ∇N_a into ``force`` (3N,) (zeroed here), or
    (MODE_STRESS) each element's volume-weighted mean Cauchy stress σ = P Fᵀ / J into ``stress``
    (M,3,3) (Pa). Returns (number of inverted points, energy); nothing is written if any point is
    inverted. Energy and force in one pass: a Newton line search needs both at each trial."""
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    D = np.empty((9, 9))
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    bad = _count_inverted(x, conn, dN, F)
    if bad:
        return bad, 0.0
    need = 0 if mode == MODE_ENERGY else 1
    if mode == MODE_FORCE:
        for k in range(force.shape[0]):
            force[k] = 0.0
    total = 0.0
    for e in range(conn.shape[0]):
        vol = 0.0
        if mode == MODE_STRESS:
            for i in range(3):
                for j in range(3):
                    stress[e, i, j] = 0.0
        for q in range(dN.shape[1]):
            J = _defgrad(x, conn, dN, e, q, F)
            v = wq[e, q]
            total += v * law_point(law[e], prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
            if mode == MODE_FORCE:
                for a in range(conn.shape[1]):
                    g0 = dN[e, q, a, 0]
                    g1 = dN[e, q, a, 1]
                    g2 = dN[e, q, a, 2]
                    for i in range(3):
                        force[edofs[e, 3 * a + i]] += v * (P[i, 0] * g0 + P[i, 1] * g1 + P[i, 2] * g2)
            elif mode == MODE_STRESS:
                vol += v
                for i in range(3):
                    for j in range(3):
                        stress[e, i, j] += v * (P[i, 0] * F[j, 0] + P[i, 1] * F[j, 1] + P[i, 2] * F[j, 2]) / J
        if mode == MODE_STRESS:
            for i in range(3):
                for j in range(3):
                    stress[e, i, j] /= vol
    return 0, total


@njit(cache=True, fastmath=False, nogil=True)
def tangent_kernel(x, conn, dN, wq, law, prm, scatter, consistent, data):
    """Element tangents Σ_q w_q Bᵀ (dP/dF) B summed into the CSR ``data`` (zeroed here) at
    ``scatter`` (M, (3n)²) (a negative position skips the entry: the fixed DOFs of a free–free
    scatter); returns the number of inverted points (nothing assembled then).

    Every law is hyperelastic, so dP/dF has major symmetry and the element block is symmetric: only
    its node blocks (a, b ≥ a) are computed, the others mirrored (half the work of the 30×30 P2
    block)."""
    nen = conn.shape[1]
    nd = 3 * nen
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    D = np.empty((9, 9))
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    T = np.empty((9, nd))
    Ke = np.empty((nd, nd))
    need = 2 if consistent else 3
    bad = _count_inverted(x, conn, dN, F)
    if bad:
        return bad
    for k in range(data.shape[0]):
        data[k] = 0.0
    for e in range(conn.shape[0]):
        for r in range(nd):
            for c in range(nd):
                Ke[r, c] = 0.0
        for q in range(dN.shape[1]):
            _defgrad(x, conn, dN, e, q, F)
            law_point(law[e], prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
            # (D B)[pj, (b,s)] = Σ_l D[pj, 3s + l] ∇N_b,l
            for r in range(9):
                for b in range(nen):
                    gb0 = dN[e, q, b, 0]
                    gb1 = dN[e, q, b, 1]
                    gb2 = dN[e, q, b, 2]
                    for s in range(3):
                        T[r, 3 * b + s] = (
                            D[r, 3 * s] * gb0 + D[r, 3 * s + 1] * gb1 + D[r, 3 * s + 2] * gb2
                        )
            # Ke[(a,p), (b,s)] += w Σ_j ∇N_a,j (D B)[3p + j, (b,s)], node blocks b >= a
            v = wq[e, q]
            for a in range(nen):
                ga0 = dN[e, q, a, 0] * v
                ga1 = dN[e, q, a, 1] * v
                ga2 = dN[e, q, a, 2] * v
                for p in range(3):
                    row = 3 * a + p
                    for c in range(3 * a, nd):
                        Ke[row, c] += ga0 * T[3 * p, c] + ga1 * T[3 * p + 1, c] + ga2 * T[3 * p + 2, c]
        for a in range(1, nen):  # lower node blocks = transposes of the upper ones
            for p in range(3):
                for c in range(3 * a):
                    Ke[3 * a + p, c] = Ke[c, 3 * a + p]
        for r in range(nd):
            for c in range(nd):
                k = scatter[e, nd * r + c]
                if k >= 0:
                    data[k] += Ke[r, c]
    return 0


_warm = False


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


def warm_up() -> None:
    """Compile (first time ever, some seconds) or load from numba's disk cache (~0.1–0.3 s) every
    kernel, with the argument types the FEM uses (read-only model arrays and positions), on one
    tet and every law; once per process. :func:`~softphantom.fem.model.build_fem` calls it, so the
    cost is paid when a model is built, not in the first Newton step or in a real-time loop."""
    global _warm
    if _warm or not HAVE_NUMBA:
        return
    conn = _ro(np.array([[0, 1, 2, 3]], dtype=np.int64))
    dN = _ro(np.array([[[[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]]]))
    wq = _ro(np.ones((1, 1)))
    x = _ro(np.array([0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]))
    edofs = _ro(np.arange(12, dtype=np.int64)[None])
    scatter = _ro(np.arange(144, dtype=np.int32)[None])
    prm = _ro(np.array([[1.0, 1.0, 0.1, 1.0]]))
    for law_id in (LAW_COROTATIONAL, LAW_NEO_HOOKEAN, LAW_YEOH):
        law = _ro(np.array([law_id], dtype=np.int64))
        for mode in (MODE_ENERGY, MODE_FORCE, MODE_STRESS):
            point_loop_kernel(x, conn, dN, wq, law, prm, edofs, mode, np.empty(12), np.empty((1, 3, 3)))
        for consistent in (True, False):
            tangent_kernel(x, conn, dN, wq, law, prm, scatter, consistent, np.empty(144))
    _warm = True
