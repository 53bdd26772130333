"""A POD + ECSW hyper-reduced model of the forward map (Farhat et al.'s energy-conserving sampling and
weighting): the probe of docs/estimation.md, not used by the package."""
from __future__ import annotations

import time

import numpy as np
from numba import njit

from softphantom.fem.kernels import law_point, scratch, _defgrad
from softphantom.fem.actuators import pressure_load, pressure_load_tangent


@njit(cache=True)
def element_forces(x, conn, dN, wq, law, prm, out):
    """out (M, 3n): each element's internal force vector."""
    F = np.empty((3, 3)); P = np.empty((3, 3)); D = np.empty((9, 9))
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    nen = conn.shape[1]
    for e in range(conn.shape[0]):
        for k in range(3 * nen):
            out[e, k] = 0.0
        for q in range(dN.shape[1]):
            _defgrad(x, conn, dN, e, q, F)
            v = wq[e, q]
            law_point(law[e], prm, e, F, P, D, 1, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
            for a in range(nen):
                g0 = dN[e, q, a, 0]; g1 = dN[e, q, a, 1]; g2 = dN[e, q, a, 2]
                for i in range(3):
                    out[e, 3 * a + i] += v * (P[i, 0] * g0 + P[i, 1] * g1 + P[i, 2] * g2)


@njit(cache=True)
def reduced_force_tangent(x, conn, dN, wq, law, prm, idx, xi, Ve, fr, Kr, need_K):
    """fr (r,) = Σ ξ_e Ve_eᵀ f_e(x); Kr (r,r) = Σ ξ_e Ve_eᵀ K_e Ve_e over the sampled elements idx.
    Ve (S, 3n, r): the basis rows of each sampled element's DOFs (zero on fixed DOFs)."""
    nen = conn.shape[1]
    nd = 3 * nen
    r = fr.shape[0]
    F = np.empty((3, 3)); P = np.empty((3, 3)); D = np.empty((9, 9))
    s0, s1, s2, s3, s4, s5, s6, s7, s8, s9 = scratch()
    T = np.empty((9, nd)); Ke = np.empty((nd, nd)); fe = np.empty(nd); KV = np.empty((nd, r))
    for i in range(r):
        fr[i] = 0.0
        for j in range(r):
            Kr[i, j] = 0.0
    bad = 0
    for s in range(idx.shape[0]):
        e = idx[s]
        w = xi[s]
        for k in range(nd):
            fe[k] = 0.0
        if need_K:
            for a in range(nd):
                for b in range(nd):
                    Ke[a, b] = 0.0
        for q in range(dN.shape[1]):
            J = _defgrad(x, conn, dN, e, q, F)
            if not J > 0.0:
                bad += 1
                continue
            v = wq[e, q]
            law_point(law[e], prm, e, F, P, D, 2 if need_K else 1, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
            for a in range(nen):
                g0 = dN[e, q, a, 0]; g1 = dN[e, q, a, 1]; g2 = dN[e, q, a, 2]
                for i in range(3):
                    fe[3 * a + i] += v * (P[i, 0] * g0 + P[i, 1] * g1 + P[i, 2] * g2)
            if need_K:
                for rr in range(9):
                    for b in range(nen):
                        gb0 = dN[e, q, b, 0]; gb1 = dN[e, q, b, 1]; gb2 = dN[e, q, b, 2]
                        for ss in range(3):
                            T[rr, 3 * b + ss] = D[rr, 3 * ss] * gb0 + D[rr, 3 * ss + 1] * gb1 + D[rr, 3 * ss + 2] * gb2
                for a in range(nen):
                    ga0 = dN[e, q, a, 0] * v; ga1 = dN[e, q, a, 1] * v; ga2 = dN[e, q, a, 2] * v
                    for p in range(3):
                        row = 3 * a + p
                        for c in range(nd):
                            Ke[row, c] += ga0 * T[3 * p, c] + ga1 * T[3 * p + 1, c] + ga2 * T[3 * p + 2, c]
        for k in range(nd):
            for i in range(r):
                fr[i] += w * Ve[s, k, i] * fe[k]
        if need_K:
            for a in range(nd):
                for j in range(r):
                    acc = 0.0
                    for b in range(nd):
                        acc += Ke[a, b] * Ve[s, b, j]
                    KV[a, j] = acc
            for i in range(r):
                for j in range(r):
                    acc = 0.0
                    for a in range(nd):
                        acc += Ve[s, a, i] * KV[a, j]
                    Kr[i, j] += w * acc
    return bad


class ROM:
    def __init__(self, fwd, snapshots_x, extra_modes=None, r_max=80, energy=1 - 1e-10):
        fem = fwd.fem
        self.fwd, self.fem = fwd, fem
        self.free = fem.free_dofs
        x0 = fem.x_rest
        U = np.stack([x - x0 for x in snapshots_x], axis=1)[self.free]
        if extra_modes is not None:
            U = np.concatenate([U, extra_modes[self.free]], axis=1)
        # POD (thin SVD)
        Q, s, _ = np.linalg.svd(U, full_matrices=False)
        e = np.cumsum(s ** 2) / np.sum(s ** 2)
        r = int(min(r_max, np.searchsorted(e, energy) + 1))
        self.V = Q[:, :r]
        self.sv = s
        self.r = r
        Vfull = np.zeros((fem.n_dof, r))
        Vfull[self.free] = self.V
        self.Vfull = Vfull
        self.x0 = x0.copy()
        self.VH = Vfull.T @ fwd.eq.H_f.toarray()  # (r, 3)
        self.ur = fwd.eq._ur_tris
        self.idx = np.arange(len(fem.tets))
        self.xi = np.ones(len(fem.tets))
        self._prep()

    def _prep(self):
        fem = self.fem
        self.Ve = np.ascontiguousarray(self.Vfull[fem.elem_dofs[self.idx]])  # (S, 3n, r)

    def train_ecsw(self, snapshots_x, tol=1e-4, verbose=True):
        """ECSW: non-negative element weights so the reduced internal force of every snapshot is matched."""
        fem = self.fem
        M = len(fem.tets)
        nd = fem.tets.shape[1] * 3
        rows = []
        b = []
        fe = np.empty((M, nd))
        Ve_all = self.Vfull[fem.elem_dofs]  # (M, nd, r)
        for x in snapshots_x:
            element_forces(x, fem.tets, fem.dN, fem.wq, fem.law_id, fem.params, fe)
            G = np.einsum("mkr,mk->rm", Ve_all, fe)  # (r, M)
            rows.append(G)
            b.append(G.sum(axis=1))
        G = np.concatenate(rows)
        b = np.concatenate(b)
        # scale rows per snapshot block? ECSW uses plain ‖Gξ − b‖ ≤ τ‖b‖
        t0 = time.perf_counter()
        xi, res = greedy_nnls(G, b, tol)
        if verbose:
            print(f"ECSW: {np.count_nonzero(xi)} of {M} elements, rel residual {res:.2e}, {time.perf_counter() - t0:.1f} s")
        self.idx = np.flatnonzero(xi)
        self.xi = xi[self.idx]
        self._prep()

    def reduced(self, q, lam, need_K=True):
        fem = self.fem
        x = self.x0 + self.Vfull @ q
        fr = np.empty(self.r); Kr = np.empty((self.r, self.r))
        bad = reduced_force_tangent(x, fem.tets, fem.dN, fem.wq, fem.law_id, fem.params, self.idx, self.xi,
                                    self.Ve, fr, Kr, need_K)
        if bad:
            return None, None, x
        R = fr - self.VH @ lam[:3]
        if lam[3] != 0.0:
            R -= lam[3] * (self.Vfull.T @ pressure_load(x, self.ur, fem.n_nodes))
            if need_K:
                T = pressure_load_tangent(x, self.ur, fem.n_nodes)
                Kr -= lam[3] * (self.Vfull.T @ (T @ self.Vfull))
        return R, Kr, x

    def solve(self, lam, q0=None, tol=1e-10, max_iter=30, reduced=None, ref=None):
        """Damped Newton on the reduced residual. ``reduced(q, lam, need_K=True) -> (R, K, x)`` (default: this
        model's hyper-reduced one; the probe passes the full assembly's); ``ref`` the force scale of
        the tolerance (default: the applied load's)."""
        reduced = reduced or self.reduced
        lam = np.asarray(lam, float)
        q = np.zeros(self.r) if q0 is None else q0.copy()
        R, K, x = reduced(q, lam)
        if ref is None:
            ref = max(np.linalg.norm(self.VH @ lam[:3]) + abs(lam[3]) * 1e-9, 1e-6)
        for it in range(max_iter):
            rn = np.linalg.norm(R)
            if rn <= tol * ref:
                return q, x, it
            dq = np.linalg.solve(K, -R)
            a = 1.0
            while True:  # trials without the tangent: it is assembled once a step is taken
                R2, _, x2 = reduced(q + a * dq, lam, False)
                if R2 is not None and np.linalg.norm(R2) < rn * (1 - 1e-4 * a) or a < 1e-3:
                    break
                a *= 0.5
            if R2 is None:
                raise RuntimeError("inverted")
            q, R, x = q + a * dq, R2, x2
            _, K, _ = reduced(q, lam)
        raise RuntimeError(f"ROM Newton did not converge at {lam}: |R| {np.linalg.norm(R):.2e} (ref {ref:.2e})")


def greedy_nnls(G, b, tol, max_el=None, batch=16):
    """Sparse NNLS (Lawson-Hanson style active set growth with NNLS on the active columns), stopping
    at ‖Gξ − b‖ ≤ tol‖b‖ (the ECSW sparse NNLS)."""
    from scipy.optimize import nnls
    m, n = G.shape
    bn = np.linalg.norm(b)
    # column scaling
    cn = np.linalg.norm(G, axis=0) + 1e-300
    Gs = G / cn
    active = []
    xi = np.zeros(n)
    res = b.copy()
    max_el = max_el or n
    while np.linalg.norm(res) > tol * bn and len(active) < max_el:
        g = Gs.T @ res
        g[active] = -np.inf
        best = np.argsort(g)[::-1][:batch]
        best = [int(k) for k in best if g[k] > 0]
        if not best:
            break
        active.extend(best)  # several columns a pass: the NNLS on the active set is the cost
        sol, _ = nnls(Gs[:, active], b, maxiter=50 * len(active))
        keep = sol > 0
        active = [a for a, kk in zip(active, keep) if kk]
        sol = sol[keep]
        res = b - Gs[:, active] @ sol
    xi[active] = sol / cn[active]
    return xi, np.linalg.norm(res) / bn
