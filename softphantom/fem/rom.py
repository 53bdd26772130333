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

from softphantom.errors import SolverError
from softphantom.fem.actuators import pressure_load, pressure_load_tangent
from softphantom.fem import kernels

NEWTON_MAX_ITER = 40
NEWTON_TOL = 1e-10  # relative reduced residual (of the applied load's and the internal force's reduced norms)
CHORD_RATE = 0.2  # a chord step contracting ‖R‖ less than this assembles the tangent anew


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False  # the kernels' one specialization (read-only model arrays and positions)
    return a


class ElementSet:
    """The elements ``elems`` of ``fem`` as a mesh of their own (local node numbering): per-element
    internal forces and tangents through the FEM's compiled kernels (:mod:`softphantom.fem.kernels`),
    scattered into dense per-element arrays instead of the global vector and matrix."""

    def __init__(self, fem, elems: np.ndarray) -> None:
        elems = np.asarray(elems, np.int64)
        nodes, inv = np.unique(fem.tets[elems], return_inverse=True)
        self.conn = _ro(inv.reshape(len(elems), -1).astype(np.int64))
        self.dofs = (3 * nodes[:, None] + np.arange(3)).ravel()  # the set's DOFs, global numbering
        self.local_dofs = (3 * self.conn[:, :, None] + np.arange(3)).reshape(len(elems), -1)  # (S, 3n)
        self.dN, self.wq = _ro(fem.dN[elems]), _ro(fem.wq[elems])
        self.law, self.prm = _ro(fem.law_id[elems]), _ro(fem.params[elems])
        S, nd = self.local_dofs.shape
        self._edofs = _ro(np.arange(S * nd, dtype=np.int64).reshape(S, nd))
        self._scatter = _ro(np.arange(S * nd * nd, dtype=np.int32).reshape(S, nd * nd))
        self.FE = np.empty((S, nd))
        self.KE = np.empty((S, nd, nd))
        self._stress = np.empty((1, 3, 3))

    def evaluate(self, x_local: np.ndarray, need_K: bool) -> bool:
        """Fill ``FE`` (S, 3n) and (``need_K``) ``KE`` (S, 3n, 3n) at the set's positions ``x_local``
        (3·nodes,); False (arrays incomplete) where an element is inverted."""
        x = _ro(x_local)
        bad, _ = kernels.point_loop_kernel(x, self.conn, self.dN, self.wq, self.law, self.prm, self._edofs,
                                           kernels.MODE_FORCE, self.FE.reshape(-1), self._stress)
        if bad:
            return False
        if need_K:
            kernels.tangent_kernel(x, self.conn, self.dN, self.wq, self.law, self.prm, self._scatter, True,
                                   self.KE.reshape(-1))
        return True


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


def _reduced_forces(fem, V: np.ndarray, elems: np.ndarray, states) -> tuple[np.ndarray, list[np.ndarray]]:
    """The elements' reduced internal forces V_eᵀ f_e(x) at each state: (Ve (c, 3n, r), [G (r, c)])."""
    es = ElementSet(fem, elems)
    Ve = V[fem.elem_dofs[elems]]  # (c, 3n, r)
    out = []
    for x in states:
        if not es.evaluate(x[es.dofs], False):
            raise SolverError("an ECSW training state has inverted elements")
        out.append(np.einsum("cnr,cn->rc", Ve, es.FE, optimize=True))
    return Ve, out


def nnls_to_tolerance(A: np.ndarray, b: np.ndarray, groups: np.ndarray, tol: float, batch: float = 0.05,
                      max_iter: int | None = None) -> tuple[np.ndarray, float]:
    """A sparse ξ ≥ 0 with every group's residual ‖(Aξ − b)_g‖ ≤ tol‖b_g‖: Lawson–Hanson's active-set
    NNLS stopped at that tolerance instead of at the exact optimum. Each outer step adds the
    columns of largest positive gradient Aᵀ(b − Aξ) (one, or ``batch`` of the active set's size);
    the least squares on the active set are solved through its Gram matrix, grown a column at a
    time. ``groups`` (rows,) the group of each row (a training state). Returns (ξ (M,), the worst
    group's relative residual).

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> A = rng.uniform(size=(40, 200))
    >>> xi, err = nnls_to_tolerance(A, A.sum(axis=1), np.zeros(40, int), 1e-6)
    >>> bool(err <= 1e-6), bool((xi >= 0).all()), int((xi > 0).sum()) <= 40
    (True, True, True)
    """
    import scipy.linalg as sla

    R, M = A.shape
    ng = int(groups.max()) + 1
    bnorm = np.sqrt(np.bincount(groups, b * b, ng))
    c = A.T @ b
    P: list[int] = []  # the active set, in the Gram matrix's order
    Gram = np.zeros((0, 0))
    xi = np.zeros(M)
    res = b.copy()

    def worst(res):
        return float(np.max(np.sqrt(np.bincount(groups, res * res, ng)) / np.maximum(bnorm, 1e-300)))

    def drop(keep):
        nonlocal P, Gram
        keep = np.asarray(keep)
        P = [P[i] for i in np.flatnonzero(keep)]
        Gram = Gram[np.ix_(keep, keep)]

    err = worst(res)
    for _ in range(max_iter or 4 * M):
        if err <= tol:
            break
        g = A.T @ res
        g[P] = -np.inf
        n_add = max(1, int(batch * len(P)))
        cand = np.argsort(g)[::-1][:n_add]
        cand = cand[g[cand] > 0]
        if not len(cand):
            break  # the exact optimum: tol is out of reach
        cross = A[:, P].T @ A[:, cand] if P else np.zeros((0, len(cand)))
        Gram = np.block([[Gram, cross], [cross.T, A[:, cand].T @ A[:, cand]]])
        P += [int(j) for j in cand]
        while True:  # Lawson–Hanson's inner loop: least squares on P, back off to stay ξ ≥ 0
            idx = np.asarray(P)
            ridge = 1e-13 * np.trace(Gram) / len(P)
            try:
                z = sla.cho_solve(sla.cho_factor(Gram + ridge * np.eye(len(P))), c[idx])
            except np.linalg.LinAlgError:
                z = np.linalg.lstsq(Gram, c[idx], rcond=None)[0]
            if (z > 0).all():
                xi[:] = 0.0
                xi[idx] = z
                break
            w = xi[idx]
            stuck = (w <= 0) & (z <= 0)  # just added and already negative: out, without a step
            if stuck.any():
                drop(~stuck)
                if not P:
                    break
                continue
            neg = z <= 0
            alpha = float(np.min(w[neg] / np.maximum(w[neg] - z[neg], 1e-300)))
            w = w + alpha * (z - w)
            keep = w > 1e-12 * max(float(w.max()), 1e-300)
            xi[idx] = np.where(keep, w, 0.0)
            drop(keep)
            if not P:
                break
        res = b - A[:, P] @ xi[P] if P else b.copy()
        err = worst(res)
    return xi, err


def ecsw_weights(fem, V: np.ndarray, states, tol: float = 1e-3, chunk: int = 1024,
                 batch: float = 0.05) -> tuple[np.ndarray, np.ndarray, float]:
    """ECSW element set and weights: ξ ≥ 0 with ‖Σ_e ξ_e g_e(x_s) − Σ_e g_e(x_s)‖ ≤ tol‖Σ_e g_e(x_s)‖
    for each training state x_s, g_e = V_eᵀ f_e the element's reduced force, on every one of the
    r·S constraint rows (no sketch: a fit exact on a sketch of the rows misses the others), by
    :func:`nnls_to_tolerance`, which stops at that tolerance with the elements it needed. The
    rows are scaled per state (each state counts alike). Returns (elements, weights, the worst
    state's relative error: ≤ tol unless the exact NNLS optimum is above it)."""
    states = [np.asarray(x, float) for x in states]
    r = V.shape[1]
    M = len(fem.tets)
    A = np.zeros((r * len(states), M))
    for a in range(0, M, chunk):
        el = np.arange(a, min(a + chunk, M))
        _, G = _reduced_forces(fem, V, el, states)
        for s, Gs in enumerate(G):
            A[s * r:(s + 1) * r, el] = Gs
    # V is zero on the fixed DOFs, so Σ_e g_e = Vᵀf(x) with every element at weight 1
    scale = 1.0 / np.maximum(np.linalg.norm(A.sum(axis=1).reshape(len(states), r), axis=1), 1e-300)
    A *= np.repeat(scale, r)[:, None]
    xi, err = nnls_to_tolerance(A, A.sum(axis=1), np.repeat(np.arange(len(states)), r), tol, batch=batch)
    idx = np.flatnonzero(xi)
    return idx, xi[idx], err


@dataclass
class ReducedSolution:
    """A converged reduced equilibrium: coordinates ``q`` (r,), loads ``lam`` (4,) N, N, N, Pa (f_x
    solved for under displacement control), ``iterations``, the last reduced tangent ``K`` (r, r)
    (for a neighbour's solve) and how many ``tangents`` were assembled."""

    q: np.ndarray
    lam: np.ndarray
    iterations: int
    K: np.ndarray
    tangents: int


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
        self._set = es = ElementSet(fem, self.elements)
        self._x0 = np.ascontiguousarray(fem.x_rest[es.dofs])
        self._Vn = np.ascontiguousarray(V[es.dofs])
        self._Ve = np.ascontiguousarray(self._Vn[es.local_dofs])  # (S, nd, r)
        un, uinv = np.unique(np.asarray(ur_tris), return_inverse=True)
        self._ur = uinv.reshape(np.shape(ur_tris)).astype(np.int64)
        udofs = (3 * un[:, None] + np.arange(3)).ravel()
        self._ux0 = fem.x_rest[udofs]
        self._Vu = np.ascontiguousarray(V[udofs])
        self._nu = len(un)

    def x(self, q: np.ndarray) -> np.ndarray:
        """(3N,) positions of the reduced state ``q``."""
        return self.x_rest + self.V @ q

    def residual(self, q: np.ndarray, lam: np.ndarray, need_K: bool = True):
        """(R (r,), K (r, r) or None, reference magnitude) of the reduced equilibrium f_int − f_ext
        at ``q``; (None, None, nan) where an element of the set is inverted."""
        es = self._set
        if not es.evaluate(self._x0 + self._Vn @ q, need_K):
            return None, None, float("nan")
        w = self.weights
        fi = np.einsum("snr,sn->r", self._Ve, es.FE * w[:, None])
        fa = self.Hr @ lam[:3]
        K = None
        if need_K:
            KV = np.matmul(es.KE, self._Ve) * w[:, None, None]  # (S, nd, r)
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
              target: float | None = None, tol: float = NEWTON_TOL, K0: np.ndarray | None = None) -> ReducedSolution:
        """The reduced equilibrium at ``lam`` (4,) from ``q0`` (default: rest): chord iterations with
        the reduced tangent ``K0`` (a neighbour's; default: the tangent at ``q0``), the tangent
        assembled anew where they contract slower than :data:`CHORD_RATE` (Newton then), each step
        backtracked on ‖R‖. Mixed control with ``h`` (r,) and ``target``: f_x (``lam[0]`` its first
        guess) is the unknown that puts hᵀq at ``target`` (the bordered system [K −h_f; hᵀ 0],
        h_f = Vᵀ H_x). Raises :class:`SolverError` if it does not converge."""
        lam = np.array(lam, float).reshape(4)
        q = np.zeros(self.r) if q0 is None else np.array(q0, float)
        mixed = h is not None
        R, K, ref = self.residual(q, lam, need_K=K0 is None)
        if R is None:
            raise SolverError(f"reduced model: start state inverted at {lam.round(4).tolist()}")
        K = K if K0 is None else K0
        fresh = K0 is None
        tangents = int(fresh)
        for it in range(NEWTON_MAX_ITER):
            gap = float(h @ q - target) if mixed else 0.0
            rn = float(np.linalg.norm(R))
            if rn <= tol * max(ref, 1e-300) and abs(gap) <= 1e-12 * (1.0 + abs(target or 0.0)):
                return ReducedSolution(q, lam, it, K, tangents)
            if mixed:
                A = np.zeros((self.r + 1, self.r + 1))
                A[:-1, :-1] = K
                A[:-1, -1] = -self.Hr[:, 0]
                A[-1, :-1] = h
                step = np.linalg.solve(A, -np.append(R, gap))
                dq, dfx = step[:-1], step[-1]
            else:
                dq, dfx = np.linalg.solve(K, -R), 0.0
            # off the constraint the full step goes onto it whatever it does to ‖R‖; on it, backtracking
            # on ‖R‖ (the constraint is linear: every step along it stays on it)
            onto = mixed and abs(gap) > 1e-12 * (1.0 + abs(target))
            a = 1.0
            while True:
                lam2 = lam.copy()
                lam2[0] += a * dfx
                R2, _, ref2 = self.residual(q + a * dq, lam2, need_K=False)
                if R2 is not None and (onto or np.linalg.norm(R2) < max(rn * (1 - 1e-4 * a), tol * ref2) or a < 1e-3):
                    break
                if a < 1e-3:
                    break
                a *= 0.5
            if R2 is None or (np.linalg.norm(R2) >= rn and not mixed):
                if fresh:
                    raise SolverError(f"reduced model: no descent along the Newton step at {lam.round(4).tolist()}")
                _, K, _ = self.residual(q, lam)  # a stale tangent: Newton's from here
                fresh, tangents = True, tangents + 1
                continue
            rate = float(np.linalg.norm(R2)) / max(rn, 1e-300)
            q, lam, R, ref = q + a * dq, lam2, R2, ref2
            if rate > CHORD_RATE:
                _, K, _ = self.residual(q, lam)
                fresh, tangents = True, tangents + 1
            else:
                fresh = False
        raise SolverError(f"reduced model: Newton did not converge at {lam.round(4).tolist()} "
                          f"(|R| {np.linalg.norm(R):.2e} of {ref:.2e})")
