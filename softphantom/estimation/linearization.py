"""Equilibrium of the phantom at given actuations and its linearization (DESIGN.md §6).

Actuations ``λ = (f_x, f_y, f_z, p_1 … p_M)``: a force (N, world axes) at the contact point, spread
by :func:`~softphantom.fem.force_actuator` (``H_f``), and the gauge pressures of the M internal
cavities (Pa, follower loads ``p_i ∂Φ_i/∂x``; the BIP: M = 1, the urethra's ``p_u``). Equilibrium:
``f_int(x) = H_f λ_f + Σ p_i ∂Φ_i/∂x`` on the free DOFs.

A :class:`Linearization` holds, at a converged equilibrium ``x_eq(λ_eq)``, what the per-sample
estimator needs: the arm-cavity volume changes ``V_eq`` (m³, relative to rest), the sensitivity
``W = ∂Φ/∂x · K⁻¹ · B`` (n_arms × (3 + M): m³/N for the three force columns, m³/Pa for the
pressure columns; ``B = ∂f_ext/∂λ``), the tracked points (markers then targets) and their sensitivity
``U_sub``, and the full ``U = K⁻¹ B`` for node positions on demand.

:class:`EquilibriumSolver` moves a linearization to new actuations: first-order predictor, then
chord iterations with the kept Cholesky factor (``K`` of an earlier state), refactoring (same
symbolic analysis) only when the chord contracts slower than ``refactor_rate``; Newton with load
stepping (:func:`~softphantom.fem.solve_static`) is the fallback.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.fem import (
    ElementInversionError,
    SparseSolver,
    cavity_volume,
    cavity_volume_gradient,
    free_tangent,
    indefinite_method,
    internal_force,
    pressure_load,
    solve_static,
)
from softphantom.fem.model import FemModel
from softphantom.records.channels import ChannelLayout

URETHRA = "urethra"
ANDERSON = 5  # depth of the Anderson mixing of the chord iterations
KRYLOV_RTOL = 1e-7  # GMRES target (preconditioned residual) for K⁻¹B solved with a stale factor
KRYLOV_ACCEPT = 1e-5  # relative true residual ‖K u − b‖/‖b‖ accepted (else refactor)
KRYLOV_MAXITER = 40
# A chord iteration (internal force + two triangular solves) costs ~1/30 of a factorization on the
# default mesh: up to CHORD_FACTOR × max_iter of them before refactoring, unless the contraction
# over the last STALL_WINDOW iterations is slower than refactor_rate and would need more than
# FACTOR_COST_ITERS further iterations to converge.
CHORD_FACTOR = 2
STALL_WINDOW = 3
FACTOR_COST_ITERS = 15
BORDERED_FACTORS = 6  # factorizations a mixed-control solve may make before it gives up
NEWTON_FIRST_ITERS = 8  # Newton iterations of the fallback's first attempt, from the chord's last state


def _pressure_text(names, p) -> str:
    return ", ".join(f"{n} {v:.0f} Pa" for n, v in zip(names, p)) or "no pressure"


@dataclass(frozen=True, eq=False)
class Linearization:
    """A converged equilibrium and its first-order sensitivities (SI; arrays read-only).

    ``lam`` (3 + M,) N,N,N,Pa…; ``x`` (3N,) m; ``V`` (n_arms,) m³ arm-cavity volume changes from rest
    (the BIP: 4 arms, M = 1); ``W`` (n_arms,3+M); ``sub_x`` (k,3) m tracked points; ``sub_U``
    (k,3,3+M); ``U`` (3N,3+M) (zero rows on fixed DOFs); ``residual`` relative force residual of ``x``;
    ``iterations`` chord/Newton iterations spent; ``refactored`` whether a new factorization was
    made; ``lin_error`` (n_arms,) m³ the previous linearization's predicted minus these converged
    volumes (NaN at start).
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
        """(n_arms,) m³ first-order arm volume changes at actuations ``lam``."""
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
    fallback. ``exact_sensitivities=False``: ``U`` (so ``W``) through the kept factor even when it
    was made at another state (no GMRES): the equilibria are as exact, the sensitivities only good
    enough for the next solve's predictor (the atlas build, which keeps only the equilibria).
    ``fallback_min_load_step``: the smallest load step of the Newton fallback before it gives up
    (a caller that expects failures, the atlas build, gives up sooner). ``layout``: the model's
    :class:`~softphantom.records.channels.ChannelLayout` (default: the FEM model's): its
    ``sensing`` cavities are the rows of ``V`` and ``W`` (the arms, then the measured cavities), its
    ``actuated`` ones the pressure loads ``λ[3:]``. Not thread-safe: one solver per thread.
    """

    def __init__(self, fem: FemModel, H_f, probe, *, solver: str = "auto", tol: float = 1e-8,
                 refactor_rate: float = 0.3, max_iter: int = 12, exact_sensitivities: bool = True,
                 fallback_min_load_step: float = 1.0 / 1024, layout: ChannelLayout | None = None) -> None:
        layout = fem.layout if layout is None else layout
        if layout is None:
            raise UserError("the FEM model has no channel layout: pass the one of its design")
        missing = [c for c in layout.channels if c not in fem.cavities]
        if missing or len(layout.sensing) < 3:
            raise UserError(f"model has cavities {list(fem.cavities)}: its channels ({', '.join(layout.channels)}) "
                            f"need {'a wall for ' + repr(missing[0]) if missing else 'at least 3 volume channels'}")
        self.layout = layout
        self.arm_names = layout.sensing  # the sensor order: the rows of V and W
        self.pressure_names = layout.actuated  # the loads λ[3:]
        pressures = self.pressure_names
        self.n_loads = 3 + len(pressures)
        self.fem = fem
        self.H_f = H_f.tocsr()
        self.probe = probe.tocsr()
        self.tol = float(tol)
        self._tol = self.tol  # of the solve in progress (a continuation's intermediate steps: looser)
        self.refactor_rate = float(refactor_rate)
        self.max_iter = int(max_iter)
        self.exact_sensitivities = bool(exact_sensitivities)
        self.fallback_min_load_step = float(fallback_min_load_step)
        self._chol = SparseSolver(solver)
        self.lin = self._chol  # the kept factor (Cholesky, or LU where the tangent is indefinite)
        self.factorizations = 0
        self.lu_factorizations = 0  # of indefinite tangents (LDLᵀ or LU)
        self._indefinite_next = False
        self._factored = False
        self._factor_at: tuple[np.ndarray, float] | None = None  # where the kept factor was made
        self.last_rate = 0.0  # mean chord contraction of the last solve
        self.krylov_iterations = 0  # GMRES iterations of the last linearization (0: direct)
        self._arm_tris = [np.asarray(fem.cavities[a]) for a in self.arm_names]
        self._p_tris = [np.asarray(fem.cavities[c]) for c in pressures]
        self._ur_tris = self._p_tris[0] if pressures == (URETHRA,) else None  # the BIP's (the reduced model)
        self._V0 = np.array([cavity_volume(fem.x_rest, t) for t in self._arm_tris])
        # Smallest meaningful force residual: round-off of the internal force (as solve_static).
        self._floor = fem.residual_floor()

    # -- pieces -----------------------------------------------------------------------------------
    def applied(self, x: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(3N,) external nodal forces at ``x`` for actuations ``lam``."""
        f = self.H_f @ lam[:3]
        for t, p in zip(self._p_tris, lam[3:]):
            if p != 0.0:
                f = f + p * pressure_load(x, t, self.fem.n_nodes)
        return f

    def residual(self, x: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, float]:
        """Free-DOF residual f_int − f_ext and its reference magnitude (N)."""
        fi = internal_force(self.fem, x)
        fa = self.applied(x, lam)
        ref = max(float(np.linalg.norm(fa)), float(np.linalg.norm(fi)))
        return (fi - fa)[self.fem.free_dofs], ref

    def _converged(self, rn: float, ref: float) -> bool:
        return rn <= max(self._tol * ref, self._floor)

    def _follower(self, p) -> list | None:
        """The pressure loads (triangles, Pa) that are on, for the tangent's follower terms."""
        out = [(t, float(v)) for t, v in zip(self._p_tris, p) if v]
        return out or None

    def _p(self, p) -> tuple[float, ...]:
        """The pressures as a tuple (a scalar: the one cavity's)."""
        return tuple(float(v) for v in np.atleast_1d(np.asarray(p, float)))

    def factorize(self, x: np.ndarray, p) -> None:
        """Factor the free tangent (with the pressures' follower terms) at ``x``; ``p`` the
        pressures (Pa, M; a scalar for one cavity)."""
        p = self._p(p)
        K = free_tangent(self.fem, x, self._follower(p))
        lin = None
        if not self._indefinite_next:
            try:
                lin = self._chol.factorize(K)
            except SolverError:  # indefinite consistent tangent (compression, pressure, a fold)
                pass
        if lin is None:
            lin = SparseSolver(indefinite_method()).factorize(K)
            self.lu_factorizations += 1
        # with an inertia (PARDISO), the next factorization goes straight to LDLᵀ while the tangents
        # stay indefinite: a failed Cholesky costs as much as a factorization
        self._indefinite_next = bool(lin.negative_eigenvalues)
        self.lin = lin
        self.factorizations += 1
        self._factored = True
        self._factor_at = (x.copy(), p)

    def keep(self) -> "KeptFactor":
        """A copy of the kept factor and where it was made, for :meth:`restore` (a walk over a grid
        that comes back to a point: its factor instead of a new factorization)."""
        if self._factor_at is None:
            raise SolverError("keep() before a factorization")
        return KeptFactor(self.lin.copy(), self._factor_at)

    def restore(self, kept: "KeptFactor") -> None:
        """Make ``kept`` (from :meth:`keep`) the kept factor again (copied: ``kept`` stays usable)."""
        lin = kept.lin.copy()
        if lin.method == self._chol.method:
            self._chol = lin  # refactored in place from here on, not ``kept``
        self.lin = lin
        self._factored = True
        self._factor_at = kept.at

    def arm_volumes(self, x: np.ndarray) -> np.ndarray:
        """(n_arms,) m³ arm-cavity volume changes from rest at ``x``."""
        return np.array([cavity_volume(x, t) for t in self._arm_tris]) - self._V0

    # -- linearization ----------------------------------------------------------------------------
    def linearize(self, x: np.ndarray, lam: np.ndarray, residual: float, iterations: int = 0,
                  refactored: bool = False, lin_error=None) -> Linearization:
        """Sensitivities at the equilibrium ``x`` (uses the kept factor as K⁻¹)."""
        fem = self.fem
        n = fem.n_nodes
        free = fem.free_dofs
        if not self._factored:
            self.factorize(x, lam[3:])
            refactored = True
        B = np.empty((fem.n_dof, self.n_loads))
        B[:, :3] = self.H_f.toarray()
        for i, t in enumerate(self._p_tris):
            B[:, 3 + i] = pressure_load(x, t, n)
        Uf = self._sensitivities(x, lam[3:], B[free])
        U = np.zeros((fem.n_dof, self.n_loads))
        U[free] = Uf
        J = np.stack([cavity_volume_gradient(x, t, n) for t in self._arm_tris])
        W = J @ U
        X = x.reshape(-1, 3)
        sub_x = self.probe @ X
        sub_U = np.stack([self.probe @ U[k::3] for k in range(3)], axis=1)  # (k,3,3+M)
        return Linearization(
            lam=lam, x=x, V=self.arm_volumes(x), W=W, sub_x=sub_x, sub_U=sub_U, U=U,
            residual=residual, iterations=iterations, refactored=refactored,
            lin_error=np.full(len(self._arm_tris), np.nan) if lin_error is None else lin_error,
        )

    def _factor_current(self, x: np.ndarray, p) -> bool:
        at = self._factor_at
        return at is not None and at[1] == self._p(p) and np.array_equal(at[0], x)

    def _sensitivities(self, x: np.ndarray, p_u, Bf: np.ndarray, exact: bool | None = None) -> np.ndarray:
        """K(x)⁻¹ B on the free DOFs: the kept factor when it was made at ``x``, else GMRES on the
        assembled tangent at ``x`` preconditioned by the kept factor (to ``KRYLOV_RTOL``); a
        refactorization where GMRES does not get there in ``KRYLOV_MAXITER``. ``exact`` None: the
        solver's ``exact_sensitivities``."""
        self.krylov_iterations = 0
        if exact is None:
            exact = self.exact_sensitivities
        if not exact or self._factor_current(x, p_u):
            return self.lin.solve(Bf)
        import scipy.sparse.linalg as spla

        K = free_tangent(self.fem, x, self._follower(self._p(p_u)))
        n = K.shape[0]
        M = spla.LinearOperator((n, n), matvec=lambda v: self.lin.solve(v), dtype=np.float64)
        X0 = self.lin.solve(Bf)  # the chord's sensitivities: the start
        out = np.empty_like(Bf)
        for j in range(Bf.shape[1]):
            counter = [0]

            def cb(_, c=counter):
                c[0] += 1

            xj, info = spla.gmres(K, Bf[:, j], x0=X0[:, j], rtol=KRYLOV_RTOL, atol=0.0, restart=KRYLOV_MAXITER,
                                  maxiter=1, M=M, callback=cb, callback_type="pr_norm")
            self.krylov_iterations += counter[0]
            bn = float(np.linalg.norm(Bf[:, j]))
            if bn > 0 and float(np.linalg.norm(K @ xj - Bf[:, j])) > KRYLOV_ACCEPT * bn:
                self.factorize(x, p_u)
                return self.lin.solve(Bf)
            out[:, j] = xj
        return out

    def exact_column(self, lin: Linearization, a: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact derivatives along load ``a`` at ``lin``'s equilibrium, whatever
        ``exact_sensitivities`` (the kept factor if made there, else GMRES preconditioned by it,
        :meth:`_sensitivities`): (∂V/∂λ_a (n_arms,), ∂sub_x/∂λ_a (k, 3), ∂x/∂λ_a (3N,)) — the column ``a``
        of ``W``, ``sub_U``, ``U``, for one load only (a Hermite atlas axis)."""
        fem = self.fem
        x, free = lin.x, fem.free_dofs
        b = self.H_f[:, a].toarray().ravel() if a < 3 else pressure_load(x, self._p_tris[a - 3], fem.n_nodes)
        u = np.zeros(fem.n_dof)
        u[free] = self._sensitivities(x, lin.lam[3:], b[free][:, None], exact=True)[:, 0]
        dV = np.array([cavity_volume_gradient(x, t, fem.n_nodes) @ u for t in self._arm_tris])
        return dV, self.probe @ u.reshape(-1, 3), u

    def rest(self) -> Linearization:
        """The linearization at rest (λ = 0), factoring there."""
        x = self.fem.x_rest.copy()
        self.factorize(x, np.zeros(len(self._p_tris)))
        return self.linearize(x, np.zeros(self.n_loads), 0.0, 0, True)

    def _chord(self, x: np.ndarray, lam: np.ndarray, r: np.ndarray, rn: float, ref: float,
               its: int, limit: int, control: "PatchControl | None" = None):
        """Chord iterations with the kept factor, Anderson-accelerated (depth ``ANDERSON``): the
        fixed-point map ``x − K₀⁻¹ r(x)``, mixed over the last steps (a nonlinear GMRES with the
        kept factor as preconditioner). A mixed step that does not lower ‖r‖ falls back to the
        plain chord step with backtracking. With a ``control`` the unknowns are (x, f_x) and each
        step solves the bordered system [K₀ −h; hᵀ 0] by block elimination (``b = K₀⁻¹h`` once
        per call, then one back-substitution a step as before): a full step lands on the patch
        displacement exactly (the constraint is linear), and so does any affine Anderson mix of
        such steps. Returns (x, lam, r, rn, ref, its, rate, ok); ``rate`` is the mean contraction
        per iteration."""
        free = self.fem.free_dofs
        lam = lam.copy()
        if control is not None:
            h = control.h[free]
            b = self.lin.solve(h)
            hb = float(h @ b)
            if hb == 0.0 or not np.isfinite(hb):  # the bordered system singular (hb < 0: an unstable
                return x, lam, r, rn, ref, its, np.inf, False  # state on the way, its step still Newton's)
            s = float(np.linalg.norm(b))  # m per N: f_x scaled like the positions it moves

        def unknowns(x, lam):
            return x[free] if control is None else np.append(x[free], lam[0] * s)

        dX: list[np.ndarray] = []
        dF: list[np.ndarray] = []
        f_prev = x_prev = None
        rn0, its0 = rn, its
        hist = [rn]
        while its < limit:
            if self._converged(rn, ref) and (control is None or control.met(x)):
                break
            # off the constraint (a predictor cut short by inverted elements): the first step
            # brings it there whatever it does to ‖r‖
            onto = control is not None and not control.met(x)
            f = self.lin.solve(-r)
            its += 1
            if control is not None:
                df = -(control.gap(x) + float(h @ f)) / hb
                f = np.append(f + df * b, df * s)
            if f_prev is not None:
                dX.append(unknowns(x, lam) - x_prev)
                dF.append(f - f_prev)
                if len(dX) > ANDERSON:
                    dX.pop(0)
                    dF.pop(0)
            f_prev, x_prev = f, unknowns(x, lam)
            step = f
            if dF:
                Fm = np.stack(dF, axis=1)
                gamma = np.linalg.lstsq(Fm, f, rcond=1e-10)[0]
                step = f - (np.stack(dX, axis=1) + Fm) @ gamma
            accepted = False
            for trial in (step, f) if dF else (f,):
                alpha = 1.0
                for _ in range(8 if trial is f else 1):
                    xt = x.copy()
                    lamt = lam.copy()
                    if control is None:
                        xt[free] += alpha * trial
                    else:
                        xt[free] += alpha * trial[:-1]
                        lamt[0] += alpha * trial[-1] / s
                        if not control.fx_bounds_N[0] <= lamt[0] <= control.fx_bounds_N[1]:
                            alpha *= 0.5  # beyond where the path's f_x can be: shorter, as for inverted elements
                            continue
                    try:
                        rt, reft = self.residual(xt, lamt)
                    except ElementInversionError:
                        alpha *= 0.5
                        continue
                    rtn = float(np.linalg.norm(rt))
                    if rtn < rn or self._converged(rtn, reft) or onto:
                        accepted = True
                        break
                    alpha *= 0.5
                if accepted:
                    break
                dX.clear()
                dF.clear()
                f_prev = x_prev = None
            if not accepted:
                return x, lam, r, rn, ref, its, np.inf, False
            x, lam, r, rn, ref = xt, lamt, rt, rtn, reft
            hist.append(rn)
            if len(hist) > STALL_WINDOW and not self._converged(rn, ref):
                rec = (rn / hist[-1 - STALL_WINDOW]) ** (1.0 / STALL_WINDOW)  # recent contraction
                need = np.log(max(self._tol * ref, self._floor) / rn) / np.log(rec) if rec < 1 else np.inf
                if rec > self.refactor_rate and need > FACTOR_COST_ITERS:
                    break  # stalled: a new factor is cheaper than the chord iterations still needed
        ok = self._converged(rn, ref) and (control is None or control.met(x))
        n = max(its - its0, 1)
        rate = (rn / max(rn0, 1e-300)) ** (1.0 / n) if rn0 > 0 else 0.0
        return x, lam, r, rn, ref, its, rate, ok

    def _newton_fallback(self, start: Linearization, x: np.ndarray, lam: np.ndarray, its: int):
        """Newton with an energy line search where the chord iterations did not converge: one
        full-load attempt from the chord's last state (usually a few iterations from there), then
        adaptive load stepping from the start state. Returns (x, its, ‖r‖, ref, refactored)."""
        sol = None
        # the first attempt steps on through an indefinite tangent with a shifted Cholesky (the
        # exact LDLᵀ step, solve_static's choice for an increment it may not cut, cost 0.6-0.8 CPU-s
        # a call on the 6 mm model and rarely converged there: the load stepping then did)
        attempts = ((x, {"min_load_step": 1.0, "max_iter": NEWTON_FIRST_ITERS, "on_indefinite": "shift"}),
                    (start.x, {"min_load_step": self.fallback_min_load_step}))
        for x0, opts in attempts:
            try:
                sol = solve_static(self.fem, self.H_f @ lam[:3], list(zip(self._p_tris, lam[3:])), x0=x0,
                                   tol=self._tol, solver=self._chol, **opts)
            except ElementInversionError:
                continue
            its += sol.iterations
            if sol.converged:
                break
        if sol is None or not sol.converged:
            raise SolverError(f"equilibrium at force {lam[:3].round(3).tolist()} N, "
                              f"{_pressure_text(self.pressure_names, lam[3:])}: "
                              f"{sol.status if sol is not None else 'elements inverted'}")
        x = sol.x.reshape(-1)
        r, ref = self.residual(x, lam)
        if self.exact_sensitivities or not self._chol.factored:
            self.factorize(x, lam[3:])
        else:  # Newton's last (maybe shifted) tangent, one step before x: the sensitivities need not be exact
            self.lin = self._chol
            self._factored = True
            self._factor_at = (np.empty(0), (float("nan"),))  # made at no state we keep
        return x, its, float(np.linalg.norm(r)), ref, True

    def solve(self, start: Linearization, lam, path: "PathCorrection | None" = None, *,
              factor_at_solution: bool = False, tol: float | None = None,
              control: "PatchControl | None" = None) -> Linearization:
        """Equilibrium at actuations ``lam`` starting from ``start``, and its linearization.

        First-order predictor, then Anderson-accelerated chord iterations with the kept factor
        (no factorization while they converge at a mean rate below ``refactor_rate``); if they
        do not, refactor at the best state and go on; Newton with load stepping is the last
        resort. The sensitivities use the exact tangent at the equilibrium: through the kept
        factor when it is current, else by GMRES on the assembled tangent preconditioned by
        the kept factor (:meth:`linearize`). ``factor_at_solution``: refactor at the equilibrium
        (unless the kept factor was made there), so its linearization is exact and the kept factor
        is the tangent there: the next solve from it starts with an Euler predictor and chord
        iterations on the tangent of its start (the atlas build). ``tol``: this solve's relative
        residual (default: the solver's ``tol``; a continuation's intermediate steps, which only
        start the next one, need less). ``control``: mixed control — f_x is an unknown (``lam[0]``
        only its first guess, replaced by the predictor's) fixed by the patch displacement
        (:class:`PatchControl`), solved by bordered chord iterations; it has no Newton fallback
        (a force-controlled one would not hold the displacement). Raises :class:`SolverError` if
        even the load-stepping fallback fails (with a ``control``: if the chord iterations do).
        """
        self._tol = self.tol if tol is None else float(tol)
        lam = np.array(lam, dtype=np.float64).reshape(self.n_loads)
        along = control.predict(start, lam) if control is not None else None  # the line's own predictor
        if control is not None:
            lam[0] = control.predict_fx(start, lam) if along is None else along[0]
        predicted_V = start.predict_volumes(lam)
        if along is not None:
            x = along[1]
        elif path is not None and path.lin is start:  # second-order predictor along the path
            x = path.predict_x(lam)
        else:
            x = start.x + start.U @ (lam - start.lam)
        refactored = False
        if not self._factored:  # no factor kept yet (nothing solved, no rest linearization): the start's
            self.factorize(start.x, start.lam[3:])
            refactored = True
        try:
            r, ref = self.residual(x, lam)
        except ElementInversionError:
            x = start.x.copy()
            r, ref = self.residual(x, lam)
        rn = float(np.linalg.norm(r))
        x, lam, r, rn, ref, its, rate, ok = self._chord(x, lam, r, rn, ref, 0, CHORD_FACTOR * self.max_iter, control)
        # force control: one refactorization, then Newton with load stepping; mixed control (no such
        # fallback): a new factor where the chord stops, up to BORDERED_FACTORS times — near the
        # arm pair's step the soft mode turns within a few iterations, and a factor from two steps
        # back no longer gives a descent direction (a modified Newton on the bordered system)
        for _ in range(1 if control is None else BORDERED_FACTORS):
            if ok:
                break
            x_was = x
            self.factorize(x, lam[3:])
            refactored = True
            x, lam, r, rn, ref, its, rate, ok = self._chord(x, lam, r, rn, ref, its, its + self.max_iter, control)
            if x is x_was:  # not one step accepted with the tangent at x: no use refactoring there again
                break
        self.last_rate = rate
        if not ok and control is not None:
            raise SolverError(f"equilibrium at patch displacement {control.target_m * 1e3:+.4f} mm, force "
                              f"{lam[1:3].round(3).tolist()} N (y, z), {_pressure_text(self.pressure_names, lam[3:])}: the bordered "
                              f"chord iterations did not converge")
        if not ok:
            x, its, rn, ref, refactored = self._newton_fallback(start, x, lam, its)
        if factor_at_solution and not self._factor_current(x, lam[3:]):
            self.factorize(x, lam[3:])
            refactored = True
        return self.linearize(x, lam, rn / max(ref, 1e-300), its, refactored,
                              lin_error=predicted_V - self.arm_volumes(x))


@dataclass(frozen=True, eq=False)
class PatchControl:
    """Mixed control of :meth:`EquilibriumSolver.solve`: f_x is the unknown that puts the patch
    displacement ``hᵀ(x − x_ref)`` at ``target_m`` (within ``tol_m``); ``h`` (3N,) is the contact
    patch's x load vector (per N of f_x), so the displacement is work-conjugate to f_x and
    ``∂ū/∂f_x = hᵀK⁻¹h > 0`` on a stable equilibrium: the path stays continuous where f_x barely
    moves and the state does."""

    h: np.ndarray
    x_ref: np.ndarray
    target_m: float
    tol_m: float
    prev: "Linearization | None" = None  # the point before the start on the same path (a secant predictor)
    fx_bounds_N: tuple[float, float] = (-np.inf, np.inf)  # an iterate's f_x outside them is a step too far
    # the path's own model: ū (m) → (f_x N, x (3N,) m), e.g. from the exact derivatives of the points
    # before (the atlas build's lines); used instead of the secant where given
    predictor: "Callable[[float], tuple[float, np.ndarray]] | None" = None

    def gap(self, x: np.ndarray) -> float:
        """m: the patch displacement at ``x`` minus the target."""
        return float(self.h @ (x - self.x_ref)) - self.target_m

    def met(self, x: np.ndarray) -> bool:
        return abs(self.gap(x)) <= self.tol_m

    def predict(self, start: Linearization, lam: np.ndarray) -> tuple[float, np.ndarray] | None:
        """(f_x N, x (3N,) m) at the target: ``predictor``'s where given, else on the secant
        through ``prev`` and ``start`` — the path parametrized by the patch displacement, so
        second-order where the state turns fast for little f_x (what the tangent's predictor is
        not); None without either (or a ``prev`` not on the same line: other loads equal) or where
        the two are at one displacement."""
        if self.predictor is not None:
            return self.predictor(self.target_m)
        p = self.prev
        if p is None or not (np.array_equal(p.lam[1:], start.lam[1:]) and np.array_equal(start.lam[1:], lam[1:])):
            return None
        du = self.gap(start.x) - self.gap(p.x)
        if du == 0.0:
            return None
        s = -self.gap(start.x) / du
        return float(start.lam[0] + s * (start.lam[0] - p.lam[0])), start.x + s * (start.x - p.x)

    def predict_fx(self, start: Linearization, lam: np.ndarray) -> float:
        """N: the f_x whose first-order state from ``start`` (the other actuations at ``lam``)
        is at the target; ``lam[0]`` where ``start``'s sensitivity is not positive."""
        dl = np.asarray(lam, float) - start.lam
        hu = self.h @ start.U
        if not hu[0] > 0:
            return float(lam[0])
        return float(start.lam[0] + (-self.gap(start.x) - hu[1:] @ dl[1:]) / hu[0])


@dataclass(frozen=True, eq=False)
class KeptFactor:
    """A copy of an :class:`EquilibriumSolver`'s factor (``lin``) and the state it was made at
    (``at``: positions (3N,) m, the pressures Pa)."""

    lin: SparseSolver
    at: tuple[np.ndarray, tuple[float, ...]]


def _path_scale(n: int) -> np.ndarray:
    """N, N, N, kPa…: a common metric for λ of ``n`` loads."""
    return np.array([1.0, 1.0, 1.0] + [1e-3] * (n - 3))
PATH_S_MIN, PATH_S_MAX = -1.0, 2.0  # extrapolation range of the path correction (in units of the last step)


@dataclass(frozen=True, eq=False)
class PathCorrection:
    """A second-order model about ``lin`` from the previous linearization ``prev``: along the
    step ``d = lin.lam − prev.lam`` the sensitivities changed by ``ΔW = lin.W − prev.W`` (and
    ``ΔU_sub``), i.e. ``∂²V/∂λ² · d ≈ ΔW``. With ``s = ⟨d, δ⟩/⟨d, d⟩`` (the position of
    ``δ = λ − lin.lam`` along the step, clipped to [PATH_S_MIN, PATH_S_MAX]) the model is
    ``V ≈ V + (W + ½ s ΔW) δ`` — exact for a quadratic map along the path, and equal to the
    first-order one at ``δ = 0`` (a converged fixed point does not move)."""

    lin: Linearization
    d: np.ndarray
    dW: np.ndarray
    dU: np.ndarray
    dU_full: np.ndarray

    @classmethod
    def between(cls, prev: Linearization, lin: Linearization) -> "PathCorrection | None":
        d = (lin.lam - prev.lam) * _path_scale(len(lin.lam))
        if float(d @ d) < 1e-8:  # (1e-4 N)²: no usable step
            return None
        return cls(lin, d / float(d @ d), lin.W - prev.W, lin.sub_U - prev.sub_U, lin.U - prev.U)

    def position(self, dlam: np.ndarray) -> float:
        return float(np.clip(self.d @ (np.asarray(dlam, float) * _path_scale(len(self.d))), PATH_S_MIN, PATH_S_MAX))

    def W(self, s: float) -> np.ndarray:
        return self.lin.W + 0.5 * s * self.dW

    def predict_volumes(self, lam: np.ndarray) -> np.ndarray:
        dl = np.asarray(lam, float) - self.lin.lam
        return self.lin.V + self.W(self.position(dl)) @ dl

    def predict_points(self, lam: np.ndarray) -> np.ndarray:
        dl = np.asarray(lam, float) - self.lin.lam
        return self.lin.sub_x + (self.lin.sub_U + 0.5 * self.position(dl) * self.dU) @ dl

    def predict_x(self, lam: np.ndarray) -> np.ndarray:
        """(3N,) m second-order node positions (the equilibrium solver's predictor)."""
        dl = np.asarray(lam, float) - self.lin.lam
        return self.lin.x + (self.lin.U + 0.5 * self.position(dl) * self.dU_full) @ dl
