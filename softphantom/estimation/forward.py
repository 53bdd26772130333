"""The forward model of one phantom at given loads: what every estimator (and calibration) solves.

:class:`ForwardModel` resolves the contact point and patch of an :class:`EstimatorConfig`, builds the
force actuator and the probe of the tracked points (markers, then targets) and keeps one
:class:`~softphantom.estimation.linearization.EquilibriumSolver`. :meth:`ForwardModel.solve` is the
converged equilibrium at actuations ``λ = (f_x, f_y, f_z, p_1 … p_M)`` (N, N, N, Pa: the force and
the design's internal cavities' pressures; the BIP: ``p_u``, the urethra's) reached by
continuation from rest (or a given start), so far-off loads converge as well as near ones. The
law and element are properties of the :class:`~softphantom.fem.FemModel`; nothing here depends on
them.
"""

from __future__ import annotations

import functools

import numpy as np

from softphantom.errors import UserError
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.linearization import EquilibriumSolver, Linearization
from softphantom.fem import fem_from_phantom, force_actuator, probe_matrix

# continuation step (N on each force component, Pa): a first-order predictor from a converged
# neighbour this close lands inside the chord iterations' basin on the default mesh
STEP_N = 1.0
STEP_PA = 10_000.0


def contact_point(model, contact) -> np.ndarray:
    """(3,) m: a named ``model.p_ext`` point or an (x, y, z) point in m."""
    if isinstance(contact, str):
        if contact not in model.p_ext:
            raise UserError(f"contact point {contact!r}: the model has {', '.join(sorted(model.p_ext))}")
        return np.asarray(model.p_ext[contact], float)
    return np.asarray(contact, float)


class ForwardModel:
    """Equilibria of ``model`` under the configured contact (see the module docstring).

    ``exact_sensitivities=False``: the solutions' sensitivities only approximate (see
    :class:`~softphantom.estimation.linearization.EquilibriumSolver`), for callers that keep only
    the equilibria; ``fallback_min_load_step`` for callers that expect failures. Attributes: ``model``, ``fem``, ``contact_point`` (3,) m, ``marker_names``, ``target_names``, ``eq`` (the
    equilibrium solver, not thread-safe), ``rest`` (the rest :class:`Linearization`), ``n_markers``.
    """

    def __init__(self, model, config: EstimatorConfig | None = None, fem=None, *,
                 exact_sensitivities: bool = True, fallback_min_load_step: float = 1.0 / 1024) -> None:
        cfg = config or EstimatorConfig()
        self.config = cfg
        self.model = model
        self.fem = fem if fem is not None else fem_from_phantom(model)
        self.contact_point = contact_point(model, cfg.contact)
        self.marker_names = tuple(model.markers)
        self.target_names = tuple(model.targets)
        if len(self.marker_names) < 3:
            raise UserError(f"the model has {len(self.marker_names)} markers; a pose needs at least 3")
        pts = [model.markers[k] for k in self.marker_names] + [model.targets[k] for k in self.target_names]
        self.H_f = force_actuator(self.fem, self.contact_point, cfg.contact_radius_m)
        self.probe = probe_matrix(self.fem, pts)
        self.eq = EquilibriumSolver(
            self.fem, self.H_f, self.probe, solver=cfg.sparse_solver, tol=cfg.tol,
            refactor_rate=cfg.refactor_rate, max_iter=cfg.max_iter, exact_sensitivities=exact_sensitivities,
            fallback_min_load_step=fallback_min_load_step, layout=model.layout,
        )
        self.layout = model.layout  # the rows of V and W (sensing), the loads λ[3:] (actuated)
        self.pressure_names = self.layout.actuated
        self.n_markers = len(self.marker_names)

    @functools.cached_property
    def rest(self) -> Linearization:
        """The rest linearization, made when first asked for (a factorization of the tangent: a
        caller that only needs the atlas key, ``atlas verify`` or a lookup, never pays for it)."""
        return self.eq.rest()

    def solve(self, lam, start: Linearization | None = None, *, factor_at_solution: bool = False,
              via_tol: float | None = None) -> Linearization:
        """Converged equilibrium (and its linearization) at ``lam`` (3 + M,) N, N, N, Pa…, reached from
        ``start`` (default: rest) in steps of at most :data:`STEP_N` / :data:`STEP_PA`.
        ``factor_at_solution``: each step ends with the tangent at its equilibrium factored (see
        :meth:`~softphantom.estimation.linearization.EquilibriumSolver.solve`). ``via_tol``: the
        relative residual of the intermediate steps (default: the configured ``tol``); the last
        step always converges to ``tol``. Raises :class:`~softphantom.errors.SolverError` naming
        the load where it fails."""
        lam = np.asarray(lam, float).reshape(self.eq.n_loads)
        lin = self.rest if start is None else start
        d = lam - lin.lam
        n = int(max(1, np.ceil(max(np.max(np.abs(d[:3])) / STEP_N, np.max(np.abs(d[3:]), initial=0.0) / STEP_PA)
                               - 1e-9)))
        for k in range(1, n + 1):
            lin = self.eq.solve(lin, lin.lam + d / (n - k + 1), factor_at_solution=factor_at_solution,
                                tol=via_tol if k < n else None)
            d = lam - lin.lam
        return lin
