"""numba kernels of the atlas estimator's per-sample step (the target: ≥ 5 kHz, p99 ≤ 1 ms).

The step's arithmetic is small — a tensor Chebyshev polynomial of a few hundred coefficients per
output, a 3-variable least squares, a 3 × 3 rigid fit — so in Python its cost is numpy call
overhead (some 60 small numpy calls per Gauss–Newton iteration). These kernels do the same
arithmetic in one compiled call each:

- :func:`eval_vj` / :func:`eval_value`: the polynomial and its gradient at λ in loops over the
  coefficients, each load first mapped to its axis's Chebyshev variable (:func:`axis_t`: affine,
  or affine in asinh(f / w) on a stretched axis) (:meth:`~softphantom.estimation.atlas.map.Atlas.volumes_reference` and
  :meth:`~softphantom.estimation.atlas.map.Atlas.value_reference` are the ``numpy.polynomial``
  references they are tested against); the gradient after :func:`contract_pressure`, which a sample does once: its pressure is
  measured, fixed during the iterations, which then sum n1·n2·n3 terms (:func:`eval_vj3`);
- :func:`gn_run`: the Gauss–Newton iterations of
  :meth:`~softphantom.estimation.atlas.estimator.AtlasEstimator.invert`, each step the minimizer of the
  volume QP of :func:`~softphantom.estimation.qp.solve_volume_qp` (same scaling and Tikhonov term)
  by a 3 × 3 Cholesky solve. That is the QP's solution when no force bound is in the way; when one
  is (or the solve breaks down) the kernel stops and returns ``NEED_QP``, and the caller takes that
  iteration with the configured QP solver (:func:`gn_update` accepts its step);
- :func:`points_pose`: the tracked points and the markers' pose — Kabsch's fit
  (:func:`rigid_fit_pose`: SVD of the 3 × 3 correlation, reflection guard) onto rest positions
  centred once, as :func:`~softphantom.pose.rigid_fit`, and its Euler angles.

Compiled on first use and cached on disk (``cache=True``: 8.9 CPU-s once per machine, then 0.25 s
to load); :func:`warm_up` compiles or loads them all when an estimator is made, so the first
real-time sample does not pay it. Serial, and they keep the GIL: a kernel that released it would
hand it, at each of a step's five calls, to any busy Python thread of the process (a Dask client's
event loop, a progress display, a Foxglove server) for up to the interpreter's switch interval
(5 ms) — measured: with a thread busy 20 % of the time beside it, the step's p99 went from 0.2 to
2.2 ms with ``nogil`` kernels and stayed at 0.2 ms without.
"""

from __future__ import annotations

import math

import numpy as np

from softphantom.estimation.qp import _SCALE_LAM, _SCALE_V
from softphantom.fem.kernels import HAVE_NUMBA, njit
from softphantom.pose.rotations import GIMBAL_EPS

# codes of gn_run / gn_update
CONTINUE, CONVERGED, NO_DESCENT, MAX_ITER, NEED_QP = 0, 1, 2, 3, 4
BACKTRACK_HALVINGS = 6  # a step that raises the misfit is halved up to this many times
_SF = float(_SCALE_LAM[0] / _SCALE_V)  # force columns of W: m³/N → mm³/N (the QP's scaling)
_SP = float(_SCALE_LAM[3] / _SCALE_V)  # pressure column: m³/Pa → mm³/kPa
_SV = float(_SCALE_V)


@njit(cache=True)
def _basis(t, n, b, d):
    """T_k(t) and T_k'(t) for k < n into b[:n], d[:n] (the recurrence of ``cheb_basis``)."""
    b[0] = 1.0
    d[0] = 0.0
    if n > 1:
        b[1] = t
        d[1] = 1.0
    for k in range(2, n):
        b[k] = 2 * t * b[k - 1] - b[k - 2]
        d[k] = 2 * b[k - 1] + 2 * t * d[k - 1] - d[k - 2]


@njit(cache=True)
def axis_t(x, lo, hi, w):
    """(t, dt/dx): the load ``x`` on [lo, hi] as the Chebyshev variable t ∈ [−1, 1] — affine, or
    with ``w`` > 0 affine in asinh(x / w) (a stretched axis: Chebyshev points clustered about zero
    load, for a map that bends sharply there; ``cheb_points`` is its inverse)."""
    if w > 0:
        a0 = math.asinh(lo / w)
        a1 = math.asinh(hi / w)
        return (2 * math.asinh(x / w) - (a0 + a1)) / (a1 - a0), 2.0 / ((a1 - a0) * math.sqrt(w * w + x * x))
    return (2 * x - (lo + hi)) / (hi - lo), 2.0 / (hi - lo)


@njit(cache=True)
def _bases(lam, lo, hi, wd, shape, na):
    """The bases (B, D, g) of the first ``na`` axes at ``lam``: row a the values and t-derivatives of
    axis a's Chebyshev polynomials (padded to the longest axis), g[a] = dt/dλ_a (:func:`axis_t`)."""
    nmax = 0
    for a in range(na):
        nmax = max(nmax, shape[a])
    B = np.empty((na, nmax))
    D = np.empty((na, nmax))
    g = np.empty(na)
    for a in range(na):
        t, ga = axis_t(lam[a], lo[a], hi[a], wd[a])
        g[a] = ga
        _basis(t, shape[a], B[a], D[a])
    return B, D, g


@njit(cache=True)
def eval_vj(C, shape, lo, hi, wd, lam, V, J):
    """Value V (m,) and Jacobian J (m, 4) per unit λ of the tensor Chebyshev polynomial with
    coefficients ``C`` (n1·n2·n3·n4, m) over the box [lo, hi] at ``lam`` (4,); ``wd`` (4,) the
    axes' stretch widths (0: affine; the pressure axis is affine, see :func:`axis_t`).

    >>> shape = np.array([2, 3, 2, 2])
    >>> C = np.zeros((24, 1)); C[4 * 2 + 0, 0] = 1.0  # T_0 · T_2(t_2) · T_0 · T_0: 2 t_2² − 1
    >>> V, J = np.empty(1), np.empty((1, 4))
    >>> eval_vj(C, shape, np.full(4, -1.0), np.full(4, 3.0), np.zeros(4), np.array([0.0, 2.0, 0.0, 0.0]), V, J)
    >>> V.tolist(), J.tolist()  # t_2 = 0.5 at λ_2 = 2 on [-1, 3]: 2·0.25 − 1; d/dλ_2 = 4 t_2 · 2/4
    ([-0.5], [[0.0, 1.0, 0.0, 0.0]])
    """
    n3 = C.shape[0] // shape[3]
    Cv = np.empty((n3, C.shape[1]))
    Cd = np.empty((n3, C.shape[1]))
    contract_pressure(C, shape, lo, hi, lam[3], Cv, Cd)
    eval_vj3(Cv, Cd, shape, lo, hi, wd, lam, V, J)


@njit(cache=True)
def eval_value(C, shape, lo, hi, wd, lam, out):
    """The value (m,) of the polynomial with coefficients ``C`` (n1·n2·n3·n4, m) at ``lam``."""
    n1, n2, n3, n4 = shape[0], shape[1], shape[2], shape[3]
    B, D, _ = _bases(lam, lo, hi, wd, shape, 4)
    m = C.shape[1]
    for o in range(m):
        out[o] = 0.0
    g = 0
    for i in range(n1):
        for j in range(n2):
            bij = B[0, i] * B[1, j]
            for k in range(n3):
                w = bij * B[2, k]
                for l in range(n4):
                    a = w * B[3, l]
                    for o in range(m):
                        out[o] += a * C[g, o]
                    g += 1


@njit(cache=True)
def contract_pressure(C, shape, lo, hi, p, Cv, Cd):
    """The polynomial at the pressure ``p`` (Pa), fixed during a sample's Gauss–Newton: ``Cv``
    (n1·n2·n3, m) its coefficients in the force axes, ``Cd`` those of its derivative per Pa. The
    iterations then evaluate a 3-D tensor (n4 times fewer terms)."""
    n4 = shape[3]
    b = np.empty(n4)
    d = np.empty(n4)
    _basis((2 * p - (lo[3] + hi[3])) / (hi[3] - lo[3]), n4, b, d)
    s = 2.0 / (hi[3] - lo[3])
    m = C.shape[1]
    for g in range(Cv.shape[0]):
        for o in range(m):
            av = 0.0
            ad = 0.0
            for l in range(n4):
                c = C[g * n4 + l, o]
                av += b[l] * c
                ad += d[l] * c
            Cv[g, o] = av
            Cd[g, o] = ad * s


@njit(cache=True)
def eval_vj3(Cv, Cd, shape, lo, hi, wd, lam, V, J):
    """:func:`eval_vj` on the polynomial contracted at ``lam[3]`` by :func:`contract_pressure`."""
    n1, n2, n3 = shape[0], shape[1], shape[2]
    B, D, gs = _bases(lam, lo, hi, wd, shape, 3)
    m = Cv.shape[1]
    for o in range(m):
        V[o] = 0.0
        for a in range(4):
            J[o, a] = 0.0
    g = 0
    for i in range(n1):
        bi, di = B[0, i], D[0, i]
        for j in range(n2):
            bij, dij, bdj = bi * B[1, j], di * B[1, j], bi * D[1, j]
            for k in range(n3):
                b3 = B[2, k]
                w0, w1, w2, w3 = bij * b3, dij * b3, bdj * b3, bij * D[2, k]
                for o in range(m):
                    c = Cv[g, o]
                    V[o] += w0 * c
                    J[o, 0] += w1 * c
                    J[o, 1] += w2 * c
                    J[o, 2] += w3 * c
                    J[o, 3] += w0 * Cd[g, o]
                g += 1
    for a in range(3):
        for o in range(m):
            J[o, a] *= gs[a]


@njit(cache=True)
def _ls_step(J, r0, x):
    """The minimizer x (3,) N of the volume QP (``solve_volume_qp``: W = J, r0 = V − V_meas, no
    pressure change) without bounds: its scaled, Tikhonov-regularised normal equations by a
    Cholesky solve. False if they are not positive definite (the QP solver then decides)."""
    m = J.shape[0]  # the arms
    Ws = np.empty((m, 4))
    for i in range(m):
        for a in range(3):
            Ws[i, a] = J[i, a] * _SF
        Ws[i, 3] = J[i, 3] * _SP
    H = np.zeros((3, 3))
    f = np.zeros(3)
    dmax = 0.0
    for a in range(4):
        s = 0.0
        for i in range(m):
            s += Ws[i, a] * Ws[i, a]
        dmax = max(dmax, s)
    dmax = max(dmax, 1e-300)
    for a in range(3):
        for b in range(3):
            s = 0.0
            for i in range(m):
                s += Ws[i, a] * Ws[i, b]
            H[a, b] = s
        s = 0.0
        for i in range(m):
            s += Ws[i, a] * (r0[i] / _SV)
        f[a] = s
    for a in range(3):
        H[a, a] += 1e-10 * H[a, a] + 1e-14 * dmax
    # Cholesky H = L Lᵀ, then L Lᵀ x = −f
    if not H[0, 0] > 0:
        return False
    l00 = math.sqrt(H[0, 0])
    l10 = H[1, 0] / l00
    l20 = H[2, 0] / l00
    s11 = H[1, 1] - l10 * l10
    if not s11 > 0:
        return False
    l11 = math.sqrt(s11)
    l21 = (H[2, 1] - l20 * l10) / l11
    s22 = H[2, 2] - l20 * l20 - l21 * l21
    if not s22 > 0:
        return False
    l22 = math.sqrt(s22)
    y0 = -f[0] / l00
    y1 = (-f[1] - l10 * y0) / l11
    y2 = (-f[2] - l20 * y0 - l21 * y1) / l22
    x[2] = y2 / l22
    x[1] = (y1 - l21 * x[2]) / l11
    x[0] = (y0 - l10 * x[1] - l20 * x[2]) / l00
    return math.isfinite(x[0]) and math.isfinite(x[1]) and math.isfinite(x[2])


@njit(cache=True)
def _misfit(V, dV):
    s = 0.0
    for i in range(V.shape[0]):
        s += (V[i] - dV[i]) ** 2
    return s


@njit(cache=True)
def gn_update(Cv, Cd, shape, lo, hi, wd, lam, V, J, cost, dV, step, blo, bhi, tol):
    """One Gauss–Newton update along ``step`` (3,) N from ``lam``: the step clipped to the force
    bounds [blo, bhi], halved while it raises the misfit (up to ``BACKTRACK_HALVINGS`` times);
    ``lam``, ``V``, ``J``, ``step`` updated in place (the polynomial as contracted by
    :func:`gn_run`). Returns (code, cost): ``NO_DESCENT`` (no
    halving lowered the misfit: λ unchanged, a bounded minimum at round-off), ``CONVERGED`` (the
    accepted step is ≤ ``tol`` N in every component) or ``CONTINUE``."""
    m = V.shape[0]  # the arms
    trial = np.empty(4)
    Vt = np.empty(m)
    Jt = np.empty((m, 4))
    trial[3] = lam[3]
    for _ in range(BACKTRACK_HALVINGS):
        for a in range(3):
            trial[a] = min(max(lam[a] + step[a], blo[a]), bhi[a])
        eval_vj3(Cv, Cd, shape, lo, hi, wd, trial, Vt, Jt)
        ct = _misfit(Vt, dV)
        if ct <= cost * (1 + 1e-12):
            for a in range(4):  # loops, not slice assignments: those cost seconds of compilation
                lam[a] = trial[a]
            for i in range(m):
                V[i] = Vt[i]
                for a in range(4):
                    J[i, a] = Jt[i, a]
            big = 0.0
            for a in range(3):
                big = max(big, abs(step[a]))
            return (CONVERGED if big <= tol else CONTINUE), ct
        for a in range(3):
            step[a] *= 0.5
    return NO_DESCENT, cost


@njit(cache=True)
def gn_run(C, Cv, Cd, shape, lo, hi, wd, lam, V, J, cost, dV, blo, bhi, tol, it0, max_iter):
    """Gauss–Newton iterations ``it0 + 1 … max_iter`` from ``lam`` on the polynomial with
    coefficients ``C``, each step the unbounded minimizer of the volume QP; ``lam``, ``V``, ``J``
    updated in place. ``it0 = 0`` starts a sample: the polynomial is contracted at the pressure
    ``lam[3]`` into ``Cv``, ``Cd`` ((n1·n2·n3, n_arms) scratch) and evaluated at ``lam`` (``cost`` is
    then ignored); later calls continue from the state they are given. Returns (code, iterations,
    cost): ``CONVERGED`` / ``NO_DESCENT`` / ``MAX_ITER``, or ``NEED_QP`` with the state at the start
    of iteration ``iterations`` when its step leaves the force bounds or the solve breaks down —
    that iteration is the QP solver's (then :func:`gn_update`)."""
    if it0 == 0:
        contract_pressure(C, shape, lo, hi, lam[3], Cv, Cd)
        eval_vj3(Cv, Cd, shape, lo, hi, wd, lam, V, J)
        cost = _misfit(V, dV)
    x = np.empty(3)
    r0 = np.empty(V.shape[0])
    for it in range(it0 + 1, max_iter + 1):
        for i in range(V.shape[0]):
            r0[i] = V[i] - dV[i]
        ok = _ls_step(J, r0, x)
        if ok:
            for a in range(3):
                if not (blo[a] - lam[a] <= x[a] <= bhi[a] - lam[a]):
                    ok = False
        if not ok:
            return NEED_QP, it, cost
        code, cost = gn_update(Cv, Cd, shape, lo, hi, wd, lam, V, J, cost, dV, x, blo, bhi, tol)
        if code != CONTINUE:
            return code, it, cost
    return MAX_ITER, max(max_iter, it0), cost


@njit(cache=True)
def points_pose(CP, shape, lo, hi, wd, lam, P0, cp, pts, t, ypr):
    """The tracked points ``pts`` (k·3,) at ``lam`` (:func:`eval_value`) and the pose of the first
    ``len(P0)`` (the markers) in one call: the rigid fit (:func:`rigid_fit_pose`), its translation
    ``t`` (3,) m and its rotation's (yaw, pitch, roll) ``ypr`` (3,) rad, as
    :func:`~softphantom.pose.ypr_from_matrix` (R = Rz(yaw)·Rx(pitch)·Ry(roll); at gimbal lock roll
    is 0 and yaw carries the rotation about z)."""
    eval_value(CP, shape, lo, hi, wd, lam, pts)
    R = np.empty((3, 3))
    rigid_fit_pose(P0, cp, pts[:3 * P0.shape[0]].reshape((P0.shape[0], 3)), R, t)
    c = math.hypot(R[2, 0], R[2, 2])
    ypr[1] = math.atan2(R[2, 1], c)
    if c < GIMBAL_EPS:
        ypr[0] = math.atan2(R[1, 0], R[0, 0])
        ypr[2] = 0.0
    else:
        ypr[0] = math.atan2(-R[0, 1], R[1, 1])
        ypr[2] = math.atan2(-R[2, 0], R[2, 2])


@njit(cache=True)
def rigid_fit_pose(P0, cp, Q, R, t):
    """Least-squares rigid transform ``Q ≈ R·P + t`` of the markers ``Q`` (k, 3), with the rest
    markers given centred (``P0`` = P − ``cp``): Kabsch by the SVD of Σ p₀ q₀ᵀ with the reflection
    guard, the arithmetic of :func:`~softphantom.pose.rigid_fit` (unit weights); R (3,3), t (3,)
    written in place."""
    k = Q.shape[0]
    cq = np.zeros(3)
    for i in range(k):
        for a in range(3):
            cq[a] += Q[i, a]
    for a in range(3):
        cq[a] /= k
    H = np.zeros((3, 3))
    for i in range(k):
        for a in range(3):
            for b in range(3):
                H[a, b] += P0[i, a] * (Q[i, b] - cq[b])
    for a in range(3):
        for b in range(3):
            H[a, b] /= k
    U, _, Vt = np.linalg.svd(H)
    # R = V · diag(1, 1, d) · Uᵀ, d = sign det(V Uᵀ) (0 → 1)
    M = Vt.T @ U.T
    det = (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
           + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))
    d = -1.0 if det < 0 else 1.0
    for a in range(3):
        for b in range(3):
            R[a, b] = Vt[0, a] * U[b, 0] + Vt[1, a] * U[b, 1] + d * Vt[2, a] * U[b, 2]
    for a in range(3):
        t[a] = cq[a] - (R[a, 0] * cp[0] + R[a, 1] * cp[1] + R[a, 2] * cp[2])


@njit(cache=True)
def force_chain(CFx, shape, lo, hi, wd, lam, J, f):
    """On a displacement-controlled first axis (``AtlasConfig.x_control``): the force ``f`` (3,) N
    at the atlas coordinates ``lam`` — f_x from its polynomial ``CFx`` (n1·n2·n3·n4, 1), f_y, f_z
    the coordinates — and ``J`` (m, 4) per unit of the coordinates turned in place into per unit
    of the loads (f, p_u) by the chain rule through q(f, p_u) (``Atlas.by_force``)."""
    v = np.empty(1)
    g = np.empty((1, 4))
    eval_vj(CFx, shape, lo, hi, wd, lam, v, g)
    f[0] = v[0]
    f[1] = lam[1]
    f[2] = lam[2]
    for i in range(J.shape[0]):
        J[i, 0] /= g[0, 0]
        for b in range(1, 4):
            J[i, b] -= J[i, 0] * g[0, b]


@njit(cache=True)
def cond_force(J):
    """Condition number of the force columns of an (n_arms, 4) sensitivity (inf if rank-deficient), as
    ``sensitivity_cond``."""
    s = np.linalg.svd(np.ascontiguousarray(J[:, :3]))[1]
    return s[0] / s[2] if s[2] > 0 else np.inf


_warm = False


def warm_up() -> None:
    """Compile (first time on a machine, some seconds) or load from numba's disk cache every kernel
    with the argument types the estimator passes; once per process."""
    global _warm
    if _warm or not HAVE_NUMBA:
        return
    shape = np.array([3, 3, 3, 2], dtype=np.int64)
    C = np.zeros((54, 4))
    C[0] = 1e-9
    C[1] = [1e-9, 2e-9, 0, 0]
    C[6] = [0, 1e-9, 1e-9, 0]
    C[18] = [0, 0, 1e-9, 1e-9]
    lo, hi = np.array([-1.0, -1, -1, -1e3]), np.array([1.0, 1, 1, 1e3])
    wd = np.array([0.1, 0.0, 0.0, 0.0])
    lam, V, J = np.zeros(4), np.empty(4), np.empty((4, 4))
    eval_vj(C, shape, lo, hi, wd, lam, V, J)
    eval_value(C, shape, lo, hi, wd, lam, np.empty(4))
    dV = np.full(4, 1e-10)
    Cv, Cd = np.empty((27, 4)), np.empty((27, 4))
    code, it, cost = gn_run(C, Cv, Cd, shape, lo, hi, wd, lam, V, J, 0.0, dV, lo[:3].copy(), hi[:3].copy(), 1e-7, 0, 3)
    gn_update(Cv, Cd, shape, lo, hi, wd, lam, V, J, cost, dV, np.zeros(3), lo[:3].copy(), hi[:3].copy(), 1e-7)
    P0 = np.eye(3) - 1 / 3
    points_pose(np.zeros((54, 9)), shape, lo, hi, wd, lam, P0, np.zeros(3), np.empty(9), np.empty(3), np.empty(3))
    cond_force(np.eye(4))
    Cx = np.zeros((54, 1))
    Cx[18] = 1.0  # f_x = T_1 of the first axis
    force_chain(Cx, shape, lo, hi, wd, lam, np.eye(4), np.empty(3))
    _warm = True
