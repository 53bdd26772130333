"""The per-sample inverse QP (paper eq. 9–10), solved by a named QP solver (daqp or quadprog).

    min_Δλ ‖V_eq + W·Δλ − V_meas‖²   s.t.  lo ≤ λ_eq,f + Δλ_f ≤ hi,   Δλ_p = p_meas − λ_eq,p

(the force's three components and one known pressure per internal cavity: M of them, the BIP 1).

Variables are scaled to N and kPa and volumes to mm³ so the Hessian WᵀW is O(1); a relative
Tikhonov term (``1e-10`` of each diagonal entry of WᵀW plus ``1e-14`` of the largest) keeps it positive definite for degenerate sensor layouts (which
:func:`~softphantom.estimation.Estimator` flags by ``cond_W``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softphantom.errors import UserError

QP_SOLVERS = ("daqp", "quadprog")
_SCALE_LAM = np.array([1.0, 1.0, 1.0, 1e3])  # N, N, N, kPa → SI (the BIP's; M pressures: kPa each)
_SCALE_V = 1e-9  # mm³ → m³


@dataclass(frozen=True)
class QPResult:
    """``dlam`` (3 + M,) SI change of the actuations; ``status`` ``"optimal"`` or the solver's reason;
    ``residual`` m³ ‖V_eq + W·Δλ − V_meas‖ at the solution; ``active`` force components held
    at a bound (3,) bool; ``iterations`` of the active-set solver."""

    dlam: np.ndarray
    status: str
    residual: float
    active: np.ndarray
    iterations: int


def solve_volume_qp(W: np.ndarray, r0: np.ndarray, dp: float, lower: np.ndarray, upper: np.ndarray,
                    solver: str = "daqp") -> QPResult:
    """Solve the estimator's QP for Δλ.

    ``W`` (n_arms, 3 + M) SI sensitivities, ``r0`` (n_arms,) m³ = V_eq − V_meas, ``dp`` Pa the fixed
    pressure changes (M; a scalar for one), ``lower``/``upper`` (3,) N bounds on the *change* of
    each force component.

    >>> W = np.eye(4) * 1e-9  # 1 mm³ per N on three sensors, 1 mm³ per Pa on the fourth
    >>> r = solve_volume_qp(W, -np.array([2., 3, 20, 0]) * 1e-9, 0.0, -np.full(3, 10.), np.full(3, 10.))
    >>> r.status, np.round(r.dlam, 6).tolist(), r.active.tolist()
    ('optimal', [2.0, 3.0, 10.0, 0.0], [False, False, True])
    """
    if solver not in QP_SOLVERS:
        raise UserError(f"QP solver must be one of {', '.join(QP_SOLVERS)}, got {solver!r}")
    W = np.asarray(W, float)
    n = W.shape[1]
    scale = _SCALE_LAM if n == 4 else np.array([1.0, 1.0, 1.0] + [1e3] * (n - 3))
    Ws = W * (scale / _SCALE_V)  # mm³ per N / per kPa
    r = np.asarray(r0, float) / _SCALE_V
    dps = np.atleast_1d(np.asarray(dp, float)) / 1e3
    if dps.shape != (n - 3,):
        raise UserError(f"QP: {dps.size} pressure change(s) for {n - 3} pressure column(s) of W")
    H = Ws.T @ Ws
    d = np.diag(H).copy()
    H[np.diag_indices(n)] += 1e-10 * d + 1e-14 * max(float(d.max()), 1e-300)
    f = Ws.T @ r
    lo = np.append(np.asarray(lower, float), dps)
    hi = np.append(np.asarray(upper, float), dps)
    if np.any(lo > hi):
        raise UserError("QP bounds: a lower bound exceeds its upper bound")
    if solver == "daqp":
        import daqp

        sense = np.array([0, 0, 0] + [5] * (n - 3), dtype=np.int32)
        x, _, flag, info = daqp.solve(H, f, np.zeros((0, n)), hi, lo, sense)
        status = "optimal" if flag in (1, 2) else f"daqp:{flag}"
        iters = int(info.get("iterations", 0)) if isinstance(info, dict) else 0
        x = np.asarray(x, float)
    else:
        import quadprog

        # quadprog: min ½xᵀGx − aᵀx s.t. Cᵀx ≥ b, the first meq rows equalities.
        m = n - 3
        C = np.zeros((n, m + 6))
        C[3:, :m] = np.eye(m)
        C[:3, m:m + 3] = np.eye(3)
        C[:3, m + 3:m + 6] = -np.eye(3)
        b = np.concatenate([dps, lo[:3], -hi[:3]])
        finite = np.isfinite(b)
        try:
            x, _, _, it, _, _ = quadprog.solve_qp(H, -f, C[:, finite], b[finite], meq=m)
            status, iters = "optimal", int(it[0])
        except ValueError as exc:  # infeasible or not positive definite
            x, status, iters = np.full(n, np.nan), f"quadprog:{exc}", 0
    if not np.all(np.isfinite(x)):
        return QPResult(np.full(n, np.nan), status if status != "optimal" else "non-finite", np.nan,
                        np.zeros(3, bool), iters)
    tol = 1e-9 * np.maximum(1.0, np.abs(hi[:3]))
    active = (x[:3] <= lo[:3] + tol) | (x[:3] >= hi[:3] - tol)
    res = float(np.linalg.norm(Ws @ x + r)) * _SCALE_V
    return QPResult(x * scale, status, res, active, iters)
