"""numba kernels of the co-rotational hot paths: internal force, strain energy and the element
tangents written straight into the CSR data array (one pass, no (M,12,12) temporary).

They compute exactly what the numpy reference in :mod:`softphantom.fem.corotational` computes
(same formulas, same order of summation in the assembly), with the polar decomposition done per
element by Higham's scaled Newton iteration X ← (γX + X⁻ᵀ/γ)/2 instead of a batched SVD: for
det F > 0 both give the unique proper rotation R = F (FᵀF)^(-1/2) (the reference's reflection guard
is then a no-op), to round-off. ``S = sym(Rᵀ F)``.

Every kernel returns the number of elements with det F <= 0 (or NaN); the caller raises
:class:`~softphantom.fem.corotational.ElementInversionError` with it. If numba is not importable,
``HAVE_NUMBA`` is False and :mod:`softphantom.fem.corotational` uses its numpy path.

Compiled on first use and cached on disk (``cache=True``); serial (``parallel=False``) so results are
deterministic and bit-identical from run to run; ``nogil=True`` so the estimator's background
equilibrium thread does not hold up the foreground (numpy/scipy release the GIL too).
"""

from __future__ import annotations

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


@njit(cache=True, fastmath=False, nogil=True)
def _count_inverted(x, tets, grads, F):
    """Elements with det F <= 0 (or NaN); checked before any output is touched."""
    bad = 0
    for e in range(tets.shape[0]):
        if not _defgrad(x, tets, grads, e, F) > 0.0:
            bad += 1
    return bad


@njit(cache=True, fastmath=False, nogil=True)
def _defgrad(x, tets, grads, e, F):
    """F = Σ_a x_a ⊗ ∇N_a of element e into F (3,3); returns det F."""
    for i in range(3):
        for j in range(3):
            F[i, j] = 0.0
    for a in range(4):
        n = tets[e, a]
        for i in range(3):
            xi = x[3 * n + i]
            for j in range(3):
                F[i, j] += xi * grads[e, a, j]
    return (
        F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
        - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
        + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0])
    )


@njit(cache=True, fastmath=False, nogil=True)
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


@njit(cache=True, fastmath=False, nogil=True)
def _stress(S, mu, lam, sig):
    tr = (S[0, 0] - 1.0) + (S[1, 1] - 1.0) + (S[2, 2] - 1.0)
    for i in range(3):
        for j in range(3):
            E = S[i, j] - (1.0 if i == j else 0.0)
            sig[i, j] = 2.0 * mu * E + (lam * tr if i == j else 0.0)


@njit(cache=True, fastmath=False, nogil=True)
def internal_force_kernel(x, tets, grads, volumes, mu, lam, edofs, out):
    """Accumulate the internal force into ``out`` (3N,) (zeroed here); returns #inverted elements.

    Nothing is written when an element is inverted (the caller raises)."""
    m = tets.shape[0]
    F = np.empty((3, 3))
    R = np.empty((3, 3))
    S = np.empty((3, 3))
    X = np.empty((3, 3))
    Y = np.empty((3, 3))
    sig = np.empty((3, 3))
    P = np.empty((3, 3))
    bad = _count_inverted(x, tets, grads, F)
    if bad:
        return bad
    for k in range(out.shape[0]):
        out[k] = 0.0
    for e in range(m):
        _defgrad(x, tets, grads, e, F)
        _polar(F, R, S, X, Y)
        _stress(S, mu[e], lam[e], sig)
        for i in range(3):
            for j in range(3):
                P[i, j] = R[i, 0] * sig[0, j] + R[i, 1] * sig[1, j] + R[i, 2] * sig[2, j]
        v = volumes[e]
        for a in range(4):
            for i in range(3):
                out[edofs[e, 3 * a + i]] += v * (
                    P[i, 0] * grads[e, a, 0] + P[i, 1] * grads[e, a, 1] + P[i, 2] * grads[e, a, 2]
                )
    return 0


@njit(cache=True, fastmath=False, nogil=True)
def strain_energy_kernel(x, tets, grads, volumes, mu, lam, out):
    """out[0] = Σ V (μ‖S − I‖² + λ/2 tr²(S − I)); returns #inverted elements."""
    m = tets.shape[0]
    F = np.empty((3, 3))
    R = np.empty((3, 3))
    S = np.empty((3, 3))
    X = np.empty((3, 3))
    Y = np.empty((3, 3))
    bad = _count_inverted(x, tets, grads, F)
    if bad:
        return bad
    total = 0.0
    for e in range(m):
        _defgrad(x, tets, grads, e, F)
        _polar(F, R, S, X, Y)
        tr = (S[0, 0] - 1.0) + (S[1, 1] - 1.0) + (S[2, 2] - 1.0)
        ee = 0.0
        for i in range(3):
            for j in range(3):
                E = S[i, j] - (1.0 if i == j else 0.0)
                ee += E * E
        total += volumes[e] * (mu[e] * ee + 0.5 * lam[e] * tr * tr)
    out[0] = total
    return 0


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


@njit(cache=True, fastmath=False, nogil=True)
def tangent_kernel(x, tets, grads, volumes, mu, lam, scatter, consistent, data):
    """Element tangents V Bᵀ (dP/dF) B summed into the CSR ``data`` (zeroed here) at ``scatter``
    (M,144); returns #inverted elements (nothing assembled then)."""
    m = tets.shape[0]
    F = np.empty((3, 3))
    R = np.empty((3, 3))
    S = np.empty((3, 3))
    X = np.empty((3, 3))
    Y = np.empty((3, 3))
    M = np.empty((3, 3))
    W = np.empty((3, 3))
    dS = np.empty((3, 3))
    sig = np.empty((3, 3))
    Ginv = np.empty((3, 3))
    D = np.empty((9, 9))
    T = np.empty((9, 12))
    bad = _count_inverted(x, tets, grads, F)
    if bad:
        return bad
    for k in range(data.shape[0]):
        data[k] = 0.0
    for e in range(m):
        _defgrad(x, tets, grads, e, F)
        _polar(F, R, S, X, Y)
        _dP_dF(R, S, mu[e], lam[e], consistent, D, M, W, dS, sig, Ginv)
        # (D B)[pj, (b,q)] = Σ_l D[pj, 3q + l] ∇N_b,l
        for r in range(9):
            for b in range(4):
                gb0 = grads[e, b, 0]
                gb1 = grads[e, b, 1]
                gb2 = grads[e, b, 2]
                for q in range(3):
                    T[r, 3 * b + q] = (
                        D[r, 3 * q] * gb0 + D[r, 3 * q + 1] * gb1 + D[r, 3 * q + 2] * gb2
                    )
        # Ke[(a,p), c] = V Σ_j ∇N_a,j (D B)[3p + j, c]
        v = volumes[e]
        for a in range(4):
            ga0 = grads[e, a, 0]
            ga1 = grads[e, a, 1]
            ga2 = grads[e, a, 2]
            for p in range(3):
                row = 12 * (3 * a + p)
                for c in range(12):
                    data[scatter[e, row + c]] += (
                        ga0 * T[3 * p, c] + ga1 * T[3 * p + 1, c] + ga2 * T[3 * p + 2, c]
                    ) * v
    return 0


_warm = False


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


def warm_up() -> None:
    """Compile (first time ever, a few seconds) or load from numba's disk cache (~0.1–0.3 s) every
    kernel, with the argument types the FEM uses (read-only model arrays and positions), on one
    tet; once per process. :func:`~softphantom.fem.model.build_fem` calls it, so the cost is paid
    when a model is built, not in the first Newton step or in a real-time loop."""
    global _warm
    if _warm or not HAVE_NUMBA:
        return
    tets = _ro(np.array([[0, 1, 2, 3]], dtype=np.int64))
    grads = _ro(np.array([[[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]]))
    one = _ro(np.ones(1))
    x = _ro(np.array([0, 0, 0, 1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]))
    edofs = _ro(np.arange(12, dtype=np.int64)[None])
    scatter = _ro(np.arange(144, dtype=np.int64)[None])
    internal_force_kernel(x, tets, grads, one, one, one, edofs, np.empty(12))
    strain_energy_kernel(x, tets, grads, one, one, one, np.empty(1))
    for consistent in (True, False):
        tangent_kernel(x, tets, grads, one, one, one, scatter, consistent, np.empty(144))
    _warm = True
