"""numba kernels of the FEM hot paths: the element loops (internal force, strain energy, tangent
written straight into the CSR data array) over the material laws' point functions.

**One point function per law** (:mod:`softphantom.fem.laws`, one file each), reached through
``law_point(law_id, prm, e, F, P, D, need, *scratch) -> W``, the dispatch on the registry's ids
that every loop inlines: at one quadrature point, from the deformation gradient F and row ``e`` of
the parameter array ``prm``, the strain energy density W (J/m³), the first Piola–Kirchhoff stress
P (``need >= 1``) and the tangent D = dP/dF (``need >= 2``; rows and columns row-major over
(i, j): ``D[3i+j, 3k+l] = ∂P_ij/∂F_kl``). The force, energy and tangent kernels all call it, so a
law is written once.

Elements: ``conn`` (M, n) node indices (n = 4 linear, 10 quadratic), ``dN`` (M, Q, n, 3) the rest
gradients ∇_X N_a at Q quadrature points, ``wq`` (M, Q) the quadrature weights times det J (m³).
F = Σ_a x_a ⊗ ∇N_a at each point.

Every kernel returns the number of quadrature points with det F <= 0 (or NaN), counted before any
output is touched; the caller raises :class:`~softphantom.fem.corotational.ElementInversionError`.
If numba is not importable, ``HAVE_NUMBA`` is False and the functions run as plain Python (slow,
same results); :mod:`softphantom.fem.corotational` then prefers its numpy path where it has one.

Compiled on first use and cached on disk (the loops that inline the laws with
:func:`~softphantom.fem._numba.law_kernel`: their cache is also keyed on the law files); serial
(``parallel=False``) so results are deterministic and bit-identical from run to run;
``nogil=True`` so the estimator's background equilibrium thread does not hold up the foreground
(numpy/scipy release the GIL too).
"""

from __future__ import annotations

import numpy as np

from softphantom.fem._numba import HAVE_NUMBA, law_kernel, njit
from softphantom.fem.laws import N_PARAMS, N_WORK, REGISTRY
from softphantom.fem.laws.corotational import polar as _polar  # noqa: F401  (tests call it)

__all__ = ["HAVE_NUMBA", "N_PARAMS", "N_WORK", "law_point", "njit", "point", "point_loop_kernel",
           "scratch", "tangent_kernel", "warm_up"]


_ARGS = "prm, e, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9"


def _dispatch(points):
    """``law_point``: one ``if law == i: return point_i(...)`` per registered law, generated from
    the registry (the same flat chain a hand-written one would be), inlined into its callers."""
    body = [f"def law_point(law, {_ARGS}):"]
    for i in range(len(points) - 1):
        body += [f"    if law == {i}:", f"        return _point{i}({_ARGS})"]
    body += [f"    return _point{len(points) - 1}({_ARGS})"]
    scope = {f"_point{i}": p for i, p in enumerate(points)}
    exec(compile("\n".join(body), f"<law_point of {len(points)} laws>", "exec"), scope)
    return njit(fastmath=False, nogil=True, inline="always")(scope["law_point"])


law_point = _dispatch(tuple(law.point for law in REGISTRY))
law_point.__doc__ = """``law_point(law_id, prm, e, F, P, D, need, s0, …, s9) -> W``: the point function of
registered law ``law_id`` (:mod:`softphantom.fem.laws.base`), inlined into the caller."""


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def scratch():
    """The N_WORK (3,3) scratch arrays of a law point function, as a tuple (static indexing: no
    array views made per call)."""
    return (np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)))


@law_kernel(fastmath=False, nogil=True)
def _point_kernel(law, prm, F, P, D, need):
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    return law_point(law, prm, 0, F, P, D, need, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)


def point(law: int, prm, F, need: int = 2):
    """(W, P, D) of law ``law`` (its id) with the parameter row ``prm`` at one F, from Python
    (tests, closed forms): the same point function the element kernels call
    (:meth:`~softphantom.fem.laws.base.Law.evaluate` is the same for one law object).

    >>> import numpy as np
    >>> from softphantom.fem.laws import NeoHookean
    >>> W, P, D = point(NeoHookean.law_id, np.array([1.0, 2.0, 0, 0]), np.eye(3))
    >>> W, float(abs(P).max()), D.shape
    (0.0, 0.0, (9, 9))
    """
    P = np.zeros((3, 3))
    D = np.zeros((9, 9))
    prm = np.pad(np.asarray(prm, float), (0, N_PARAMS - len(prm)))[None]
    W = _point_kernel(int(law), prm, np.ascontiguousarray(F, dtype=np.float64), P, D, int(need))
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


@law_kernel(fastmath=False, nogil=True)
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


@law_kernel(fastmath=False, nogil=True)
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
    for law_id in range(len(REGISTRY)):
        law = _ro(np.array([law_id], dtype=np.int64))
        for mode in (MODE_ENERGY, MODE_FORCE, MODE_STRESS):
            point_loop_kernel(x, conn, dN, wq, law, prm, edofs, mode, np.empty(12), np.empty((1, 3, 3)))
        for consistent in (True, False):
            tangent_kernel(x, conn, dN, wq, law, prm, scatter, consistent, np.empty(144))
    _warm = True
