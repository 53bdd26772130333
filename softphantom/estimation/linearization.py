"""Equilibrium of the phantom at given actuations and its linearization (DESIGN.md §6).

Actuations ``λ = (f_x, f_y, f_z, p_u)``: a force (N, world axes) at the contact point, spread by
:func:`~softphantom.fem.force_actuator` (``H_f``), and the urethra gauge pressure (Pa, a follower
load ``p_u ∂Φ_u/∂x``). Equilibrium: ``f_int(x) = H_f λ_f + p_u ∂Φ_u/∂x`` on the free DOFs.

A :class:`Linearization` holds, at a converged equilibrium ``x_eq(λ_eq)``, what the per-sample
estimator needs: the arm-cavity volume changes ``V_eq`` (m³, relative to rest), the sensitivity
``W = ∂Φ/∂x · K⁻¹ · B`` (4 × 4: m³/N for the three force columns, m³/Pa for the pressure
column; ``B = ∂f_ext/∂λ``), the tracked points (markers then targets) and their sensitivity
``U_sub``, and the full ``U = K⁻¹ B`` for node positions on demand.

:class:`EquilibriumSolver` moves a linearization to new actuations: first-order predictor, then
chord iterations with the kept Cholesky factor (``K`` of an earlier state), refactoring (same
symbolic analysis) only when the chord contracts slower than ``refactor_rate``; Newton with load
stepping (:func:`~softphantom.fem.solve_static`) is the fallback.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.fem import (
    ElementInversionError,
    SparseSolver,
    cavity_volume,
    cavity_volume_gradient,
    free_tangent,
    internal_force,
    pressure_load,
    solve_static,
)
from softphantom.fem.model import FemModel
from softphantom.estimation.types import ARM_NAMES

URETHRA = "urethra"


@dataclass(frozen=True, eq=False)
class Linearization:
    """A converged equilibrium and its first-order sensitivities (SI; arrays read-only).

    ``lam`` (4,) N,N,N,Pa; ``x`` (3N,) m; ``V`` (4,) m³ arm-cavity volume changes from rest;
    ``W`` (4,4); ``sub_x`` (k,3) m tracked points; ``sub_U`` (k,3,4); ``U`` (3N,4) (zero rows on
    fixed DOFs); ``residual`` relative force residual of ``x``; ``iterations`` chord/Newton
    iterations spent; ``refactored`` whether a new factorization was made; ``lin_error``
    (4,) m³ the previous linearization's predicted minus these converged volumes (NaN at start).
    """

    lam: np.ndarray
    x: np.ndarray
    V: np.ndarray
    W: np.ndarray
    sub_x: np.ndarray
    sub_U: np.ndarray
    U: np.ndarray
    residual: float
    iterations: int = 0
    refactored: bool = False
    lin_error: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))

    def __post_init__(self) -> None:
        for k in ("lam", "x", "V", "W", "sub_x", "sub_U", "U", "lin_error"):
            a = np.array(getattr(self, k), dtype=np.float64)
            a.flags.writeable = False
            object.__setattr__(self, k, a)

    def predict_volumes(self, lam: np.ndarray) -> np.ndarray:
        """(4,) m³ first-order arm volume changes at actuations ``lam``."""
        return self.V + self.W @ (np.asarray(lam, float) - self.lam)

    def predict_points(self, lam: np.ndarray) -> np.ndarray:
        """(k,3) m first-order positions of the tracked points at ``lam``."""
        return self.sub_x + self.sub_U @ (np.asarray(lam, float) - self.lam)

    def predict_nodes(self, lam: np.ndarray) -> np.ndarray:
        """(N,3) m first-order node positions at ``lam``."""
        return (self.x + self.U @ (np.asarray(lam, float) - self.lam)).reshape(-1, 3)


class EquilibriumSolver:
    """Equilibria and linearizations of one model (keeps one Cholesky factor between calls).

    ``H_f`` (3N,3) sparse force actuator, ``probe`` (k,N) sparse interpolation of the tracked
    points, ``tol`` relative force residual, ``refactor_rate`` the chord contraction above which
    the tangent is refactored, ``max_iter`` chord/Newton iterations before the load-stepping
    fallback. Not thread-safe: one solver per thread.
    """

    def __init__(self, fem: FemModel, H_f, probe, *, solver: str = "auto", tol: float = 1e-8,
                 refactor_rate: float = 0.3, max_iter: int = 12) -> None:
        if URETHRA not in fem.cavities or any(a not in fem.cavities for a in ARM_NAMES):
            raise UserError(f"model lacks cavities {[a for a in (*ARM_NAMES, URETHRA) if a not in fem.cavities]}")
        self.fem = fem
        self.H_f = H_f.tocsr()
        self.probe = probe.tocsr()
        self.tol = float(tol)
        self.refactor_rate = float(refactor_rate)
        self.max_iter = int(max_iter)
        self._chol = SparseSolver(solver)
        self.lin = self._chol  # the kept factor (Cholesky, or LU where the tangent is indefinite)
        self.factorizations = 0
        self.lu_factorizations = 0
        self._factored = False
        self._arm_tris = [np.asarray(fem.cavities[a]) for a in ARM_NAMES]
        self._ur_tris = np.asarray(fem.cavities[URETHRA])
        self._V0 = np.array([cavity_volume(fem.x_rest, t) for t in self._arm_tris])
        # Smallest meaningful force residual: round-off of the internal force (as solve_static).
        unit = np.bincount(
            fem.tets.reshape(-1),
            weights=np.repeat((2 * fem.mu + fem.lam) * fem.volumes, 4)
            * np.linalg.norm(fem.grads, axis=2).reshape(-1),
            minlength=fem.n_nodes,
        )
        self._floor = 16 * np.finfo(float).eps * float(np.linalg.norm(np.repeat(unit, 3)[fem.free_dofs]))

    # -- pieces -----------------------------------------------------------------------------------
    def applied(self, x: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(3N,) external nodal forces at ``x`` for actuations ``lam``."""
        f = self.H_f @ lam[:3]
        if lam[3] != 0.0:
            f = f + lam[3] * pressure_load(x, self._ur_tris, self.fem.n_nodes)
        return f

    def residual(self, x: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, float]:
        """Free-DOF residual f_int − f_ext and its reference magnitude (N)."""
        fi = internal_force(self.fem, x)
        fa = self.applied(x, lam)
        ref = max(float(np.linalg.norm(fa)), float(np.linalg.norm(fi)))
        return (fi - fa)[self.fem.free_dofs], ref

    def _converged(self, rn: float, ref: float) -> bool:
        return rn <= max(self.tol * ref, self._floor)

    def factorize(self, x: np.ndarray, p_u: float) -> None:
        """Factor the free tangent (with the urethra pressure's follower term) at ``x``."""
        K = free_tangent(self.fem, x, [(self._ur_tris, float(p_u))] if p_u else None)
        try:
            self.lin = self._chol.factorize(K)
        except SolverError:  # indefinite consistent tangent (compression, pressure): LU
            self.lin = SparseSolver("splu").factorize(K)
            self.lu_factorizations += 1
        self.factorizations += 1
        self._factored = True

    def arm_volumes(self, x: np.ndarray) -> np.ndarray:
        """(4,) m³ arm-cavity volume changes from rest at ``x``."""
        return np.array([cavity_volume(x, t) for t in self._arm_tris]) - self._V0

    # -- linearization ----------------------------------------------------------------------------
    def linearize(self, x: np.ndarray, lam: np.ndarray, residual: float, iterations: int = 0,
                  refactored: bool = False, lin_error=None) -> Linearization:
        """Sensitivities at the equilibrium ``x`` (uses the kept factor as K⁻¹)."""
        fem = self.fem
        n = fem.n_nodes
        free = fem.free_dofs
        if not self._factored:
            self.factorize(x, lam[3])
            refactored = True
        B = np.empty((fem.n_dof, 4))
        B[:, :3] = self.H_f.toarray()
        B[:, 3] = pressure_load(x, self._ur_tris, n)
        Uf = self.lin.solve(B[free])
        U = np.zeros((fem.n_dof, 4))
        U[free] = Uf
        J = np.stack([cavity_volume_gradient(x, t, n) for t in self._arm_tris])
        W = J @ U
        X = x.reshape(-1, 3)
        sub_x = self.probe @ X
        sub_U = np.stack([self.probe @ U[k::3] for k in range(3)], axis=1)  # (k,3,4)
        return Linearization(
            lam=lam, x=x, V=self.arm_volumes(x), W=W, sub_x=sub_x, sub_U=sub_U, U=U,
            residual=residual, iterations=iterations, refactored=refactored,
            lin_error=np.full(4, np.nan) if lin_error is None else lin_error,
        )

    def rest(self) -> Linearization:
        """The linearization at rest (λ = 0), factoring there."""
        x = self.fem.x_rest.copy()
        self.factorize(x, 0.0)
        return self.linearize(x, np.zeros(4), 0.0, 0, True)

    def solve(self, start: Linearization, lam) -> Linearization:
        """Equilibrium at actuations ``lam`` starting from ``start``, and its linearization.

        Raises :class:`SolverError` if even the load-stepping fallback fails.
        """
        lam = np.array(lam, dtype=np.float64).reshape(4)
        free = self.fem.free_dofs
        predicted_V = start.predict_volumes(lam)
        x = start.x + start.U @ (lam - start.lam)
        refactored = False
        its = 0
        ok = False
        try:
            r, ref = self.residual(x, lam)
        except ElementInversionError:
            x = start.x.copy()
            r, ref = self.residual(x, lam)
        rn = float(np.linalg.norm(r))
        while its < self.max_iter:
            if self._converged(rn, ref):
                ok = True
                break
            d = self.lin.solve(-r)
            its += 1
            alpha, accepted = 1.0, False
            for _ in range(8):
                xt = x.copy()
                xt[free] += alpha * d
                try:
                    rt, reft = self.residual(xt, lam)
                except ElementInversionError:
                    alpha *= 0.5
                    continue
                rtn = float(np.linalg.norm(rt))
                if rtn < rn or self._converged(rtn, reft):
                    accepted = True
                    break
                alpha *= 0.5
            if accepted:
                rate = rtn / rn
                x, r, rn, ref = xt, rt, rtn, reft
            else:
                rate = np.inf
            if rate > self.refactor_rate and not self._converged(rn, ref):
                self.factorize(x, lam[3])
                refactored = True
        if not ok and self._converged(rn, ref):
            ok = True
        if not ok:  # robust fallback: Newton with adaptive load stepping from the start state
            sol = solve_static(
                self.fem, self.H_f @ lam[:3], [(self._ur_tris, lam[3])], x0=start.x,
                tol=self.tol, solver=self._chol,
            )
            if not sol.converged:
                raise SolverError(f"equilibrium at force {lam[:3].round(3).tolist()} N, urethra "
                                  f"{lam[3]:.0f} Pa: {sol.status}")
            x = sol.x.reshape(-1)
            its += sol.iterations
            r, ref = self.residual(x, lam)
            rn = float(np.linalg.norm(r))
            self.factorize(x, lam[3])
            refactored = True
        return self.linearize(x, lam, rn / max(ref, 1e-300), its, refactored,
                              lin_error=predicted_V - self.arm_volumes(x))
