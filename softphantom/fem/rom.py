"""A reduced-order forward model: Galerkin projection of the equilibrium on a snapshot basis,
hyper-reduced by energy-conserving sampling and weighting (ECSW, Farhat et al. 2014).

The state is x = x_rest + V q with V (3N, r) orthonormal on the free DOFs (zero on the fixed
ones): POD of converged full solves and of their exact load sensitivities K⁻¹B (:func:`pod_basis`).
The reduced internal force Vᵀf(x) = Σ_e V_eᵀ f_e(x) is replaced by Σ_{e∈S} ξ_e V_eᵀ f_e(x) over a
small element set S with weights ξ ≥ 0 (:func:`ecsw_weights`), and its tangent likewise, so a
reduced Newton step costs a pass over S, not over the mesh. Applied loads are exact: the contact
patch's load is constant (VᵀH), the urethra pressure a follower load on its triangles only.
The model is an approximation whose error the caller measures (the atlas's offline stage checks
it against full solves, :mod:`softphantom.estimation.offline`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from softphantom.errors import SolverError
from softphantom.fem.actuators import pressure_load, pressure_load_tangent
from softphantom.fem.kernels import _defgrad, law_point, njit, scratch

NEWTON_MAX_ITER = 40
NEWTON_TOL = 1e-10  # relative reduced residual (of the applied load's and the internal force's reduced norms)


@njit(cache=True, fastmath=False, nogil=True)
def element_kernel(x, conn, dN, wq, law, prm, elems, need_K, FE, KE):
    """For each element ``elems[s]``: its internal force FE[s] (3n,) and (``need_K``) consistent
    tangent KE[s] (3n, 3n) at positions ``x`` (3N,) through ``conn`` (M, n). Returns the number of
    inverted quadrature points (the arrays are then incomplete)."""
    nen = conn.shape[1]
    nd = 3 * nen
    F = np.empty((3, 3))
    P = np.empty((3, 3))
    D = np.empty((9, 9))
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    T = np.empty((9, nd))
    bad = 0
    for s in range(elems.shape[0]):
        e = elems[s]
        for k in range(nd):
            FE[s, k] = 0.0
        if need_K:
            for a in range(nd):
                for b in range(nd):
                    KE[s, a, b] = 0.0
        for qp in range(dN.shape[1]):
            J = _defgrad(x, conn, dN, e, qp, F)
            if not J > 0.0:
                bad += 1
                continue
            v = wq[e, qp]
            law_point(law[e], prm, e, F, P, D, 2 if need_K else 1, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
            for a in range(nen):
                g0 = dN[e, qp, a, 0]
                g1 = dN[e, qp, a, 1]
                g2 = dN[e, qp, a, 2]
                for i in range(3):
                    FE[s, 3 * a + i] += v * (P[i, 0] * g0 + P[i, 1] * g1 + P[i, 2] * g2)
            if need_K:
                for r in range(9):
                    for b in range(nen):
                        gb0 = dN[e, qp, b, 0]
                        gb1 = dN[e, qp, b, 1]
                        gb2 = dN[e, qp, b, 2]
                        for c in range(3):
                            T[r, 3 * b + c] = D[r, 3 * c] * gb0 + D[r, 3 * c + 1] * gb1 + D[r, 3 * c + 2] * gb2
                for a in range(nen):
                    ga0 = dN[e, qp, a, 0] * v
                    ga1 = dN[e, qp, a, 1] * v
                    ga2 = dN[e, qp, a, 2] * v
                    for p in range(3):
                        row = 3 * a + p
                        for c in range(3 * a, nd):  # upper node blocks; mirrored below (hyperelastic: symmetric)
                            KE[s, row, c] += ga0 * T[3 * p, c] + ga1 * T[3 * p + 1, c] + ga2 * T[3 * p + 2, c]
        if need_K:
            for a in range(1, nen):
                for p in range(3):
                    for c in range(3 * a):
                        KE[s, 3 * a + p, c] = KE[s, c, 3 * a + p]
    return bad


def pod_basis(D: np.ndarray, rtol: float = 1e-12, r_max: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(V (n, r) orthonormal, singular values) of the columns of ``D`` (n, m): the leading left
    singular vectors whose dropped energy Σσ² is below ``rtol`` of the total (at most ``r_max``).

    >>> import numpy as np
    >>> D = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    >>> pod_basis(D)[0].shape
    (5, 1)
    """
    U, s, _ = np.linalg.svd(D, full_matrices=False)
    e = s ** 2
    tail = e.sum() - np.cumsum(e)
    r = int(np.searchsorted(-tail, -rtol * e.sum()) + 1)
    r = min(r, len(s), r_max or len(s))
    return np.ascontiguousarray(U[:, :r]), s


def _local(fem, elems: np.ndarray):
    """The nodes of ``elems``, their local connectivity, and the DOFs (3·nodes) in global numbering."""
    nodes, inv = np.unique(fem.tets[elems], return_inverse=True)
    conn = inv.reshape(len(elems), -1).astype(np.int64)
    dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
    return nodes, conn, dofs


def element_projections(fem, V: np.ndarray, x: np.ndarray, chunk: int = 1024):
    """Yields (elements, G (r, c)): each element's reduced internal force V_eᵀ f_e(x), in chunks."""
    nd = 3 * fem.tets.shape[1]
    for a in range(0, len(fem.tets), chunk):
        el = np.arange(a, min(a + chunk, len(fem.tets)))
        FE = np.empty((len(el), nd))
        if element_kernel(x, fem.tets, fem.dN, fem.wq, fem.law_id, fem.params, el, False, FE, np.empty((1, 1, 1))):
            raise SolverError("an ECSW training state has inverted elements")
        Ve = V[fem.elem_dofs[el]]  # (c, nd, r)
        yield el, np.einsum("cnr,cn->rc", Ve, FE)


def ecsw_weights(fem, V: np.ndarray, states, tol: float = 1e-3, sketch: int | None = None,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """ECSW element set and weights: ξ ≥ 0 with ‖Σ_e ξ_e g_e(x_s) − Σ_e g_e(x_s)‖ ≤ tol‖Σ_e g_e(x_s)‖
    for each training state x_s, g_e = V_eᵀ f_e the element's reduced force (blocks normalised per
    state). The r·S constraint rows are compressed by a seeded Gaussian sketch of ``sketch`` rows
    (default 3r), and the NNLS is solved exactly on the sketch (Lawson–Hanson: at most ``sketch``
    elements); the sketch doubles until every state's own relative error meets ``tol``.
    Returns (elements, weights, the worst state's relative error)."""
    r = V.shape[1]
    M = len(fem.tets)
    rng = np.random.default_rng(seed)
    k = min(sketch or 3 * r, M)
    states = list(states)
    while True:
        A = np.zeros((k, M))
        bs = []
        for x in states:
            Om = rng.standard_normal((k, r)) / np.sqrt(k)
            b = np.zeros(r)
            blocks = list(element_projections(fem, V, x))
            for _, G in blocks:
                b += G.sum(axis=1)
            s = 1.0 / max(np.linalg.norm(b), 1e-300)
            for el, G in blocks:
                A[:, el] += Om @ (G * s)
            bs.append((blocks, b))
        rhs = A.sum(axis=1)
        xi, _ = nnls(A, rhs, maxiter=20 * M)
        err = 0.0
        for blocks, b in bs:
            approx = sum(G @ xi[el] for el, G in blocks)
            err = max(err, float(np.linalg.norm(approx - b) / max(np.linalg.norm(b), 1e-300)))
        if err <= tol or k >= M:
            idx = np.flatnonzero(xi)
            return idx, xi[idx], err
        k = min(2 * k, M)


@dataclass
class ReducedSolution:
    """A converged reduced equilibrium: coordinates ``q`` (r,), loads ``lam`` (4,) N, N, N, Pa (f_x
    solved for under displacement control), Newton ``iterations``."""

    q: np.ndarray
    lam: np.ndarray
    iterations: int


class ReducedModel:
    """The hyper-reduced Galerkin model of ``fem`` (see the module docstring). ``V`` (3N, r) the
    basis (zero rows on fixed DOFs), ``H_f`` (3N, 3) the contact patch's load per N, ``ur_tris``
    the urethra's triangles (its pressure load), ``elements``/``weights`` the ECSW set (default: every
    element with weight 1, the plain Galerkin model)."""

    def __init__(self, fem, V: np.ndarray, H_f, ur_tris: np.ndarray, elements: np.ndarray | None = None,
                 weights: np.ndarray | None = None) -> None:
        self.fem = fem
        self.V = np.ascontiguousarray(V)
        self.r = V.shape[1]
        self.x_rest = fem.x_rest
        self.Hr = np.asarray(H_f.T @ V).T  # (r, 3): the patch's load per N, reduced
        self.elements = np.arange(len(fem.tets)) if elements is None else np.asarray(elements, np.int64)
        self.weights = np.ones(len(self.elements)) if weights is None else np.asarray(weights, float)
        nodes, conn, dofs = _local(fem, self.elements)
        self._conn = conn
        self._x0 = np.ascontiguousarray(fem.x_rest[dofs])
        self._Vn = np.ascontiguousarray(V[dofs])
        loc = np.arange(len(self.elements))
        ldofs = (3 * conn[:, :, None] + np.arange(3)).reshape(len(loc), -1)
        self._Ve = np.ascontiguousarray(self._Vn[ldofs])  # (S, nd, r)
        self._dN = np.ascontiguousarray(fem.dN[self.elements])
        self._wq = np.ascontiguousarray(fem.wq[self.elements])
        self._law = np.ascontiguousarray(fem.law_id[self.elements])
        self._prm = np.ascontiguousarray(fem.params[self.elements])
        for a in (self._dN, self._wq, self._law, self._prm):
            a.flags.writeable = False  # one numba specialization (read-only arrays) for every model
        un, uinv = np.unique(np.asarray(ur_tris), return_inverse=True)
        self._ur = uinv.reshape(np.shape(ur_tris)).astype(np.int64)
        udofs = (3 * un[:, None] + np.arange(3)).ravel()
        self._ux0 = fem.x_rest[udofs]
        self._Vu = np.ascontiguousarray(V[udofs])
        self._nu = len(un)
        nd = self._Ve.shape[1]
        self._FE = np.empty((len(loc), nd))
        self._KE = np.empty((len(loc), nd, nd))
        self._lidx = loc

    def x(self, q: np.ndarray) -> np.ndarray:
        """(3N,) positions of the reduced state ``q``."""
        return self.x_rest + self.V @ q

    def residual(self, q: np.ndarray, lam: np.ndarray, need_K: bool = True):
        """(R (r,), K (r, r) or None, reference magnitude) of the reduced equilibrium f_int − f_ext
        at ``q``; (None, None, nan) where an element of the set is inverted."""
        xl = self._x0 + self._Vn @ q
        if element_kernel(xl, self._conn, self._dN, self._wq, self._law, self._prm, self._lidx, need_K,
                          self._FE, self._KE):
            return None, None, float("nan")
        w = self.weights
        fi = np.einsum("snr,sn->r", self._Ve, self._FE * w[:, None])
        fa = self.Hr @ lam[:3]
        K = None
        if need_K:
            KV = np.matmul(self._KE, self._Ve) * w[:, None, None]  # (S, nd, r)
            S, nd, r = self._Ve.shape
            K = self._Ve.reshape(S * nd, r).T @ KV.reshape(S * nd, r)
        if lam[3] != 0.0:
            xu = self._ux0 + self._Vu @ q
            fa = fa + lam[3] * (self._Vu.T @ pressure_load(xu, self._ur, self._nu))
            if need_K:
                T = pressure_load_tangent(xu, self._ur, self._nu)
                K = K - lam[3] * (self._Vu.T @ (T @ self._Vu))
        ref = max(float(np.linalg.norm(fa)), float(np.linalg.norm(fi)))
        return fi - fa, K, ref

    def solve(self, lam, q0: np.ndarray | None = None, *, h: np.ndarray | None = None,
              target: float | None = None, tol: float = NEWTON_TOL) -> ReducedSolution:
        """The reduced equilibrium at ``lam`` (4,) by damped Newton from ``q0`` (default: rest).
        Mixed control with ``h`` (r,) and ``target``: f_x (``lam[0]`` its first guess) is the unknown
        that puts hᵀq at ``target`` (the bordered system [K −h_f; hᵀ 0], h_f = Vᵀ H_x).
        Raises :class:`SolverError` if it does not converge."""
        lam = np.array(lam, float).reshape(4)
        q = np.zeros(self.r) if q0 is None else np.array(q0, float)
        mixed = h is not None
        R, K, ref = self.residual(q, lam)
        if R is None:
            raise SolverError(f"reduced model: start state inverted at {lam.round(4).tolist()}")
        for it in range(NEWTON_MAX_ITER):
            gap = float(h @ q - target) if mixed else 0.0
            rn = float(np.linalg.norm(R))
            if rn <= tol * max(ref, 1e-300) and abs(gap) <= 1e-12 * (1.0 + abs(target or 0.0)) and it > 0:
                return ReducedSolution(q, lam, it)
            if mixed:
                A = np.zeros((self.r + 1, self.r + 1))
                A[:-1, :-1] = K
                A[:-1, -1] = -self.Hr[:, 0]
                A[-1, :-1] = h
                step = np.linalg.solve(A, -np.append(R, gap))
                dq, dfx = step[:-1], step[-1]
            else:
                dq, dfx = np.linalg.solve(K, -R), 0.0
            a = 1.0
            while True:  # backtracking on the residual (the constraint is linear: any step keeps it affine)
                lam2 = lam.copy()
                lam2[0] += a * dfx
                R2, _, ref2 = self.residual(q + a * dq, lam2, need_K=False)
                if R2 is not None and (np.linalg.norm(R2) < max(rn * (1 - 1e-4 * a), tol * ref2) or a < 1e-3):
                    break
                if a < 1e-3:
                    raise SolverError(f"reduced model: inverted along the Newton step at {lam.round(4).tolist()}")
                a *= 0.5
            q, lam = q + a * dq, lam2
            R, K, ref = self.residual(q, lam)
            if R is None:
                raise SolverError(f"reduced model: inverted at {lam.round(4).tolist()}")
        raise SolverError(f"reduced model: Newton did not converge at {lam.round(4).tolist()} "
                          f"(|R| {np.linalg.norm(R):.2e} of {ref:.2e})")
