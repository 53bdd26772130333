"""The real-time estimator on an atlas (:class:`AtlasEstimator`).

Per sample, a Gauss–Newton iteration in the 3 force components (the urethra pressure is measured)
on the atlas's polynomial volumes, each step the bounded QP of
:func:`~softphantom.estimation.qp.solve_volume_qp` with the polynomial's Jacobian; the points and
the full field come from the same polynomials at the solution. No refresh and no thread: the step
is compiled (:mod:`~softphantom.estimation.atlas.kernels`, on the atlas's public
:class:`~softphantom.estimation.atlas.map.KernelView`), tens of microseconds a sample.
"""

from __future__ import annotations

import math
import time

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.estimation.atlas import kernels as ak
from softphantom.estimation.atlas.build import check_atlas_cavities
from softphantom.estimation.atlas.catalogue import Found, atlas_key, find_or_build
from softphantom.estimation.atlas.config import AtlasConfig
from softphantom.estimation.atlas.map import Atlas, AtlasPatches, AtlasStack
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.estimator import (
    EstimatorState, check_sample, measured_pressures, pose_and_shifts, repeat_last, rest_estimate, sensitivity_cond,
)
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.qp import solve_volume_qp
from softphantom.estimation.types import Estimate
from softphantom.pose import DegenerateMarkersError, Pose6, rigid_fit

#: The held-out goals of the default model's shipped atlas (docs/accuracy.md): force N, position
#: mm, angle deg, the near-urethra target mm (``atlas check``; :meth:`AtlasEstimator.rest_check`).
GOALS = {"force_N": 0.05, "pos_mm": 0.05, "ang_deg": 0.1, "near_urethra_mm": 0.02}

GN_MAX_ITER = 12
GN_TOL_N = 1e-7
FACE_TOL_N = 1e-9  # a Gauss–Newton that ends this close to a piece's shared f_y face goes on in the neighbour


class AtlasEstimator(EstimatorState):
    """The real-time estimator on an :class:`~softphantom.estimation.atlas.map.Atlas` (see the module docstring): ``step(measurement)
    → Estimate`` with no background work; ``node_positions()`` the full field of the last estimate.

    On an :class:`~softphantom.estimation.atlas.map.AtlasStack` (several actuated cavities) each
    sample's Gauss–Newton runs on the stack's piece mixed at the measured further pressures; the
    state λ is (3 + M,).

    ``Estimate.in_envelope`` is False when a measured pressure lies outside the atlas's range,
    when the best fit wants a force beyond an envelope face that is tighter than the configured
    force bounds (the estimate is then the best one clamped to the envelope), or when it lies in a
    grid cell the build could not solve (the estimate then comes from the extrapolated fill).
    """

    kind = "atlas"

    def __init__(self, model, config: EstimatorConfig | None = None,
                 atlas: Found | Atlas | AtlasPatches | AtlasStack | AtlasConfig | None = None,
                 *, cache_dir=None, scheduler: str | None = None, n_workers: int | None = None,
                 max_build_s: float | None = None, require_full: bool = False, draft: bool = False) -> None:
        self.config = cfg = config or EstimatorConfig()
        self.model = model
        self.cavity = check_atlas_cavities(model)
        fwd = ForwardModel(model, cfg)
        self.forward = fwd
        self.layout = fwd.layout  # the phantom's channels: the estimates' volumes (sensing) and pressures
        self.arm_names = self.layout.sensing
        self.cavities = self.layout.actuated  # p_1 (the atlas's pressure axis), then a stack's further ones
        if not isinstance(atlas, (Found, Atlas, AtlasPatches, AtlasStack)):
            atlas = find_or_build(model, cfg, atlas, model_dir=cache_dir, scheduler=scheduler, n_workers=n_workers,
                                  fwd=fwd, max_build_s=max_build_s, require_full=require_full, draft=draft)
        found = atlas if isinstance(atlas, Found) else None
        atlas = found.atlas if found is not None else atlas
        if require_full and atlas.draft:
            from softphantom.estimation.atlas.build import DraftRefused

            raise DraftRefused("--require-full, but the atlas given is a draft (atlas build --draft)")
        stack = atlas if isinstance(atlas, AtlasStack) else None
        n_p = 1 + (len(stack.config.further_min_kPa) if stack is not None else 0)
        if n_p != len(self.cavities):
            raise UserError(f"atlas of {n_p} internal pressure{'s' * (n_p > 1)}, the model has "
                            f"{len(self.cavities)} actuated cavities ({', '.join(self.cavities)}); rebuild it")
        every = stack.all_pieces if stack is not None else (
            atlas.patches if isinstance(atlas, AtlasPatches) else (atlas,))
        # the catalogue found it by these keys; an atlas given directly is checked here
        if found is None and any(a.key != atlas_key(model, cfg, a.config) for a in every):
            raise UserError("atlas built for another model, law, contact or envelope; rebuild it")
        self.atlas = atlas
        self._unsolved = bool(atlas.unsolved)  # asked per sample by _inside
        self._stack = stack
        # the pieces along f_y (a stack's: its first level's, whose f_y ranges every level shares)
        pieces = every[:stack.n_pieces] if stack is not None else every
        self._pieces = pieces
        self.marker_names, self.target_names = fwd.marker_names, fwd.target_names
        nm = fwd.n_markers
        rest = fwd.probe @ fwd.fem.x_rest.reshape(-1, 3)  # the tracked points at rest: no tangent to factor
        self.rest_markers = rest[:nm].copy()
        self.rest_targets = rest[nm:].copy()
        elo, ehi = atlas.config.lower, atlas.config.upper
        ulo, uhi = np.array(cfg.force_min_N), np.array(cfg.force_max_N)
        self._lo = np.maximum(ulo, elo[:3])
        self._hi = np.minimum(uhi, ehi[:3])
        if np.any(self._lo > self._hi):
            raise UserError(f"force bounds {cfg.force_min_N}..{cfg.force_max_N} N do not meet the atlas "
                            f"envelope {atlas.config.force_min_N}..{atlas.config.force_max_N} N")
        self._bounds = (self._lo.tolist(), self._hi.tolist())
        self._env_lo = np.where(elo[:3] > ulo, self._lo, -np.inf)  # envelope faces inside the bounds
        self._env_hi = np.where(ehi[:3] < uhi, self._hi, np.inf)
        self._faces = list(zip(self._env_lo.tolist(), self._env_hi.tolist()))
        self._p_ranges = [(float(elo[3]), float(ehi[3]))] + [
            (lo * 1e3, hi * 1e3) for lo, hi in zip(atlas.config.further_min_kPa, atlas.config.further_max_kPa)]
        # each piece's force bounds: the estimator's, f_y cut to the piece's range
        self._piece_bounds = []
        for a in pieces:
            lo, hi = self._lo.copy(), self._hi.copy()
            lo[1], hi[1] = max(lo[1], a.config.force_min_N[1]), min(hi[1], a.config.force_max_N[1])
            self._piece_bounds.append((lo, hi))
        try:  # the rest markers centred once for the per-sample fit (rigid_fit checks they span a plane)
            rigid_fit(self.rest_markers, self.rest_markers)
            self._cp = self.rest_markers.mean(axis=0)
            self._P0 = np.ascontiguousarray(self.rest_markers - self._cp)
        except DegenerateMarkersError:
            self._cp = self._P0 = None
        ak.warm_up()
        self.reset()

    @property
    def lam(self) -> np.ndarray:
        """(3 + M,) the current actuation estimate: force N (3), the internal pressures Pa (the
        atlas's coordinates of it are ``coords``)."""
        return np.r_[self.atlas.forces(self._lam), self._lam[3:]]

    @property
    def coords(self) -> np.ndarray:
        """(3 + M,) the last estimate in the atlas's coordinates (``Atlas.coords``)."""
        return self._lam.copy()

    def reset(self) -> None:
        """Back to rest."""
        self._lam = np.zeros(3 + len(self.cavities))
        self._last = rest_estimate(self.target_names, self.atlas.volumes(self._lam)[1], self.layout)

    def rest_check(self) -> dict:
        """The estimate at rest (zero volumes, zero internal pressures) against the rest state, which
        it should return: its force (N, magnitude), position (mm) and angle (deg, largest
        component), whether it lies inside the envelope, the atlas's own largest volume at zero
        load (mm³: its interpolation error there, where the grid has no point), and ``ok`` when
        all are within the atlas goals (:data:`GOALS`, or the error its reduced-model build
        measured, when larger). A coarse grid misses it: the estimates of a phantom at rest then
        carry that offset."""
        p = 0.0 if self._stack is None else np.zeros(len(self.cavities))
        zero = self.atlas.coords(np.zeros(3), p)
        lam, _, inside, _, _, _ = self.invert(np.zeros(len(self.arm_names)), p, start=zero)
        xyz_ypr = self._pose(lam)[0].to_mm_deg()
        off = (self.atlas.provenance or {}).get("offline") if hasattr(self.atlas, "provenance") else None
        limits = {"force_N": GOALS["force_N"], "pos_mm": max(GOALS["pos_mm"], float((off or {}).get(
            "check_max_points_mm", 0.0))), "ang_deg": GOALS["ang_deg"]}
        got = {"force_N": float(np.linalg.norm(self.atlas.forces(lam))), "pos_mm": float(np.abs(xyz_ypr[:3]).max()),
               "ang_deg": float(np.abs(xyz_ypr[3:]).max())}
        return {**got, "in_envelope": bool(inside),
                "dV_at_zero_mm3": float(np.abs(self.atlas.volumes(zero)[0]).max() * 1e9), "limits": limits,
                "ok": bool(inside) and all(got[k] <= limits[k] for k in limits)}

    def node_positions(self) -> np.ndarray:
        """(N,3) m node positions of the last estimate (the atlas's field; evaluated when asked,
        not per sample)."""
        return self.atlas.nodes(self._lam)

    def _start(self, p_Pa, start) -> tuple[np.ndarray, bool]:
        """The first iterate: the start's forces (default: the last estimate's) clipped to the
        bounds, the measured pressures (M,) clipped to the envelope; and whether they were inside."""
        given = np.atleast_1d(np.asarray(p_Pa, float)).tolist()
        if len(given) != len(self._p_ranges):
            raise SolverError(f"{len(given)} pressures for the atlas's {len(self._p_ranges)}")
        p = [min(max(v, lo), hi) for v, (lo, hi) in zip(given, self._p_ranges)]
        f = (self._lam if start is None else np.asarray(start, float))[:3].tolist()
        lam = np.array([min(max(v, lo), hi) for v, lo, hi in zip(f, self._bounds[0], self._bounds[1])] + p)
        return lam, p == given

    def _inside(self, lam: np.ndarray, inside: bool) -> bool:
        tol = 1e-6
        for f, (lo, hi) in zip(lam[:3].tolist(), self._faces):
            if f <= lo + tol or f >= hi - tol:  # at an envelope face inside the bounds: clamped
                return False
        if inside and self._unsolved:
            return self.atlas.solved_at(lam)  # where the atlas was filled, not solved
        return inside

    def invert(self, dV, p_Pa, start=None) -> tuple[np.ndarray, str, bool, np.ndarray, np.ndarray, int]:
        """Loads that best explain the volumes ``dV`` (n_arms,) m³ at the internal pressures ``p_Pa``
        (Pa: a number for one cavity, (M,) for a stack):
        (λ (3 + M,), QP status, in_envelope, V (n_arms,), J (n_arms,4) ∂V/∂(q, f_y, f_z, p_1), Gauss–Newton
        iterations), λ and
        ``start`` in the atlas's coordinates (:meth:`Atlas.coords`; the force is
        :meth:`Atlas.forces` of λ).

        Gauss–Newton from ``start`` (default: the last estimate) on the polynomial volumes, each
        step the volume QP with its exact Jacobian, a step that raises the misfit halved
        (:func:`~softphantom.estimation.atlas.kernels.gn_run`). With no force bound in the way the
        QP's minimizer is a 3 × 3 solve inside the kernel; an iteration whose step meets a bound is
        solved by the configured QP solver (``EstimatorConfig.qp_solver``).
        :meth:`invert_reference` is the same iteration in numpy, every step by the QP solver."""
        lam, inside = self._start(p_Pa, start)
        dV = np.asarray(dV, float)
        k = self._piece_index(lam[1])
        best, seen = None, set()
        while k not in seen:  # one piece, then its neighbour while the fit stops on their shared face
            seen.add(k)
            res = self._invert_piece(k, lam.copy(), dV)
            if best is not None and res[2] >= best[2]:
                break
            best = res
            lam = res[0]
            lo, hi = self._piece_bounds[k]
            if k > 0 and lam[1] <= lo[1] + FACE_TOL_N:
                k -= 1
            elif k < len(self._pieces) - 1 and lam[1] >= hi[1] - FACE_TOL_N:
                k += 1
        lam, code, _, V, J, it = best
        status = "gn:max_iter" if code == ak.MAX_ITER else "optimal"
        return lam, status, self._inside(lam, inside), V, J, it

    def _piece_index(self, f_y: float) -> int:
        return self.atlas.index(f_y) if len(self._pieces) > 1 else 0

    def _piece(self, k: int, lam: np.ndarray):
        """Piece ``k`` at λ: the atlas's own, or a stack's mixed at the further pressures λ[4:]."""
        return self._pieces[k] if self._stack is None else self._stack.piece_at(k, lam[4:])

    def _invert_piece(self, k: int, lam: np.ndarray, dV: np.ndarray):
        """Gauss–Newton on piece ``k`` from ``lam`` (f_y clamped into it): (λ, code, misfit m⁶, V, J, iterations)."""
        at = self._piece(k, lam)
        lo, hi = self._piece_bounds[k]
        lam[1] = min(max(lam[1], lo[1]), hi[1])
        kv = at.kernel
        m = kv.V.shape[1]  # the arms
        V, J = np.empty(m), np.empty((m, 4))
        n3 = kv.n_force_terms
        lam4 = lam if len(lam) == 4 else lam[:4]  # a view: the kernels update the force in place
        poly = (np.empty((n3, m)), np.empty((n3, m)), *kv.box, lam4, V, J)
        code, it, cost = ak.gn_run(kv.V, *poly, 0.0, dV, lo, hi, GN_TOL_N, 0, GN_MAX_ITER)
        while code == ak.NEED_QP:  # a force bound is in the way of this iteration's step: the QP's
            qp = solve_volume_qp(J, V - dV, 0.0, lo - lam[:3], hi - lam[:3], self.config.qp_solver)
            if qp.status != "optimal":
                raise SolverError(f"QP {qp.status}")
            code, cost = ak.gn_update(*poly, cost, dV, qp.dlam[:3].copy(), lo, hi, GN_TOL_N)
            if code == ak.CONTINUE:
                code, it, cost = ak.gn_run(kv.V, *poly, cost, dV, lo, hi, GN_TOL_N, it, GN_MAX_ITER)
        return lam, code, cost, V, J, it

    def invert_reference(self, dV, p_Pa: float, start=None):
        """:meth:`invert` as it was before the kernels (numpy evaluation, every Gauss–Newton step
        by the QP solver): the reference for the tests and ``bench_estimate.py``'s ratio."""
        at = self.atlas
        lam, inside = self._start(p_Pa, start)
        dV = np.asarray(dV, float)
        V, J = at.volumes_reference(lam)
        cost = float(np.sum((V - dV) ** 2))
        status = "gn:max_iter"
        it = 0
        for it in range(1, GN_MAX_ITER + 1):
            qp = solve_volume_qp(J, V - dV, 0.0, self._lo - lam[:3], self._hi - lam[:3], self.config.qp_solver)
            if qp.status != "optimal":
                raise SolverError(f"QP {qp.status}")
            step = qp.dlam[:3]
            # backtracking: Gauss–Newton on a mildly non-linear map; halve a step that raises the misfit
            for _ in range(ak.BACKTRACK_HALVINGS):
                trial = lam.copy()
                trial[:3] = np.clip(lam[:3] + step, self._lo, self._hi)
                Vt, Jt = at.volumes_reference(trial)
                ct = float(np.sum((Vt - dV) ** 2))
                if ct <= cost * (1 + 1e-12):
                    break
                step = 0.5 * step
            else:
                status = "optimal"  # no descent left: a (bounded) minimum at round-off
                break
            lam, V, J, cost = trial, Vt, Jt, ct
            if np.max(np.abs(step)) <= GN_TOL_N:
                status = "optimal"
                break
        return lam, status, self._inside(lam, inside), V, J, it

    def _pose(self, lam: np.ndarray):
        """(Pose6, target shifts) at ``lam``: the tracked points by the kernel, the markers' rigid
        fit by :func:`~softphantom.estimation.atlas.kernels.rigid_fit_pose`."""
        at = self._piece(self._piece_index(lam[1]), lam)
        lam4 = lam if len(lam) == 4 else np.ascontiguousarray(lam[:4])
        if self._P0 is None:  # rest markers that rigid_fit refuses: let it raise its error, as before
            return pose_and_shifts(self.rest_markers, self.rest_targets, self.target_names, at.points(lam4))
        kv = at.kernel
        pts, t, ypr = np.empty(kv.P.shape[1]), np.empty(3), np.empty(3)
        ak.points_pose(kv.P, *kv.box, lam4, self._P0, self._cp, pts, t, ypr)
        shifts = pts.reshape(-1, 3)[len(self._P0):] - self.rest_targets
        return Pose6(t, ypr), dict(zip(self.target_names, shifts))

    def step(self, m, skipped: int = 0) -> Estimate:
        """Estimate the state for one measurement; a bad sample repeats the last state with
        ``status="rejected:<why>"`` (as the refresh estimator)."""
        return self._step(m, skipped, reference=False)

    def step_reference(self, m, skipped: int = 0) -> Estimate:
        """:meth:`step` as it was before the kernels (the same estimate to round-off; for
        ``bench_estimate.py``'s old/new ratio and the tests)."""
        return self._step(m, skipped, reference=True)

    def _step(self, m, skipped: int, reference: bool) -> Estimate:
        t0 = time.perf_counter()
        why = check_sample(m, self.arm_names)
        if why:
            return repeat_last(self._last, m, f"rejected:{why}", t0, skipped)
        try:
            inv = self.invert_reference if reference else self.invert
            p_Pa = measured_pressures(m, self.cavities)  # one cavity's unless a stack's
            given = dict(zip(self.cavities, p_Pa.tolist()))
            lam, status, inside, V, J, it = inv(m.dV, float(p_Pa[0]) if self._stack is None else p_Pa)
        except SolverError as exc:
            return repeat_last(self._last, m, f"failed:{exc}", t0, skipped)
        at = self._piece(self._piece_index(lam[1]), lam)
        lam4 = lam if len(lam) == 4 else np.ascontiguousarray(lam[:4])
        # the force and the sensitivity to the loads, whatever the atlas's first axis
        if reference:
            force, J = at.forces(lam4), at.by_force(lam4, J)
            pose, shifts = pose_and_shifts(self.rest_markers, self.rest_targets, self.target_names,
                                           at.value_reference(at.cP, lam4))
            cond = sensitivity_cond(J)
        else:
            force = lam[:3].copy()
            if at.displacement_x:
                ak.force_chain(at.kernel.Fx, *at.kernel.box, lam4, J, force)
            pose, shifts = self._pose(lam)
            cond = float(ak.cond_force(J))
        dV = np.array(m.dV, float)
        est = Estimate(
            t=float(m.t), force=force, p_urethra=float(m.p_urethra), pose=pose, target_shift=shifts,
            volume_pred=V, volume_meas=dV, cond_W=cond, qp_status=status,
            step_time=time.perf_counter() - t0, skipped=int(skipped), in_envelope=inside,
            extra={"qp_residual_m3": math.dist(V, dV), "gn_iterations": it,
                   **({"pressures_Pa": given} if self.cavities != ("urethra",) else {})},
            layout=self.layout,
        )
        self._lam = lam
        self._last = est
        return est
