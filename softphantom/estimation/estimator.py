"""The real-time inverse estimator (DESIGN.md §6, paper eq. 8–10).

Per sample (the foreground, a fraction of a millisecond): with the latest :class:`Linearization`
``(x_eq, λ_eq, W, U_sub)``, solve the QP ``min ‖V_eq + W·Δλ − ΔV_meas‖²`` with the force bounds
and ``Δλ_p`` fixed by the measured pressures of the internal cavities (the BIP: the urethra's); ``λ = λ_eq + Δλ``; the tracked points
(markers, targets) move to ``x_sub = x_eq,sub + U_sub·Δλ``; the pose is the rigid fit of the
markers. The equilibrium at the new ``λ`` (converged, warm-started, refactoring only when needed:
:class:`EquilibriumSolver`) refreshes the linearization — inside :meth:`Estimator.step` in
``"sync"`` mode (deterministic), on a background thread in ``"async"`` mode (numpy, scipy and
CHOLMOD release the GIL in their heavy parts). On a steady input the refreshes converge to the
exact solution: a Gauss–Newton iteration on the volumes with the exact tangent.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from softphantom.errors import SolverError
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.linearization import Linearization, PathCorrection
from softphantom.estimation.qp import solve_volume_qp
from softphantom.estimation.types import Estimate
from softphantom.records.channels import ChannelLayout
from softphantom.pose import Pose6, rigid_fit

PATH_ITERATIONS = 4  # fixed-point passes of the QP on the path-corrected W (see PathCorrection)
TRUST_GROW_BELOW = 0.15  # a refresh's linearization error / its volume change: below, the trust region doubles
TRUST_SHRINK_ABOVE = 0.3  # above, it halves (never below trust_N / trust_Pa)
HISTORY = 10_000  # refreshes kept in Estimator.refresh_times / lin_errors


class History:
    """The latest ``size`` values of a per-refresh quantity (each of ``width`` numbers, or a scalar
    for width 0) in arrays allocated once: its memory does not change however long a run lasts
    (a list of small arrays would grow by ~170 bytes a refresh: 4 MB/h at 6 refreshes/s). ``len``,
    slicing and ``np.asarray`` give the kept values, oldest first.

    >>> h = History(width=0, size=3)
    >>> for i in range(5):
    ...     h.append(float(i))
    >>> len(h), h[:].tolist(), h[1:].tolist(), h.total
    (3, [2.0, 3.0, 4.0], [3.0, 4.0], 5)
    """

    def __init__(self, width: int = 0, size: int = HISTORY) -> None:
        self._a = np.full((size, width) if width else size, np.nan)
        self.total = 0

    def append(self, value) -> None:
        self._a[self.total % len(self._a)] = value
        self.total += 1

    def values(self) -> np.ndarray:
        n = len(self._a)
        if self.total <= n:
            return self._a[:self.total].copy()
        k = self.total % n
        return np.concatenate([self._a[k:], self._a[:k]])

    def __len__(self) -> int:
        return min(self.total, len(self._a))

    def __getitem__(self, item):
        return self.values()[item]

    def __array__(self, dtype=None, copy=None):
        v = self.values()
        return v if dtype is None else v.astype(dtype)


@dataclass(frozen=True)
class NoiseBound:
    """1-σ errors propagated from the sensor noise through W⁺ (unconstrained least squares):
    ``force_N`` (3,), ``pose`` (6,) in m, m, m, rad, rad, rad (x, y, z, yaw, pitch, roll),
    ``target_m`` per target (3,). ``cov_force`` (3,3) N²."""

    force_N: np.ndarray
    pose: np.ndarray
    target_m: dict[str, np.ndarray]
    cov_force: np.ndarray


def pose_and_shifts(rest_markers: np.ndarray, rest_targets: np.ndarray, target_names, points: np.ndarray):
    """(Pose6, {target: shift (3,) m}) from tracked points (markers first, then targets): the
    pose is the rigid fit of the markers onto their rest positions (exact for a rigid motion).

    >>> rest = np.array([[0.03, 0, 0], [0, 0.025, 0], [0, 0, 0.03], [-0.03, 0, 0.01]])
    >>> pose, sh = pose_and_shifts(rest, np.zeros((1, 3)), ["c"], np.vstack([rest, [[0, 0, 0]]]) + [0, 0.002, 0])
    >>> (np.round(pose.to_mm_deg(), 9) + 0.0).tolist(), (np.round(sh["c"], 9) + 0.0).tolist()
    ([0.0, 2.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.002, 0.0])
    """
    nm = rest_markers.shape[0]
    pose = Pose6.from_transform(rigid_fit(rest_markers, points[:nm]))
    shifts = {k: points[nm + i] - rest_targets[i] for i, k in enumerate(target_names)}
    return pose, shifts


def noise_bound(lin: Linearization, rest_markers: np.ndarray, target_names, sigma_dV_m3,
                sigma_p_Pa: float = 0.0, lam=None) -> NoiseBound:
    """1-σ errors from independent volume noise ``sigma_dV_m3`` (scalar or (n_arms,), m³) and urethra
    pressure noise, propagated through the least-squares inverse ``W_f⁺`` of ``lin`` (bounds
    inactive), then through ``U_sub`` to the pose (rigid fit of the first ``len(rest_markers)``
    tracked points, Jacobian by central differences about ``lam``, default ``lin.lam``) and to the
    targets (the tracked points after the markers, named ``target_names``)."""
    nm = len(rest_markers)
    n = lin.W.shape[1]  # 3 + M loads
    Wf, wp = lin.W[:, :3], lin.W[:, 3:]
    Wp = np.linalg.pinv(Wf)  # (3, n_arms)
    s = np.broadcast_to(np.asarray(sigma_dV_m3, float), (len(Wf),))
    # δf = W_f⁺ (δV − W_p δp), each pressure's noise sigma_p_Pa
    g = Wp @ wp  # (3, M)
    cov = Wp @ np.diag(s**2) @ Wp.T + g @ g.T * sigma_p_Pa**2
    # pose and targets: linear in δλ = (δf, δp); Jacobian of the pose by central differences
    cov_l = np.zeros((n, n))
    cov_l[:3, :3] = cov
    cov_l[3:, 3:] = np.eye(n - 3) * sigma_p_Pa**2
    cov_l[:3, 3:] = -g * sigma_p_Pa**2
    cov_l[3:, :3] = cov_l[:3, 3:].T
    lam0 = lin.lam if lam is None else np.asarray(lam, float)
    Jp = np.zeros((6, n))
    for j in range(n):
        h = np.zeros(n)
        h[j] = 1e-3 if j < 3 else 1.0
        a = Pose6.from_transform(rigid_fit(rest_markers, lin.predict_points(lam0 + h)[:nm]))
        b = Pose6.from_transform(rigid_fit(rest_markers, lin.predict_points(lam0 - h)[:nm]))
        Jp[:, j] = (np.r_[a.xyz, a.ypr] - np.r_[b.xyz, b.ypr]) / (2 * h[j])
    pose = np.sqrt(np.diag(Jp @ cov_l @ Jp.T))
    targets = {}
    for i, k in enumerate(target_names):
        Ut = lin.sub_U[nm + i]  # (3,3+M)
        targets[k] = np.sqrt(np.diag(Ut @ cov_l @ Ut.T))
    return NoiseBound(np.sqrt(np.diag(cov)), pose, targets, cov)


def check_sample(m, arm_names: tuple[str, ...]) -> str:
    """'' for a usable sample (one volume per volume channel of ``arm_names``, a layout's
    ``sensing``), else the rejection reason."""
    if getattr(m, "status", "ok") != "ok":
        return str(m.status)
    dV = np.asarray(m.dV, dtype=float)
    if dV.shape != (len(arm_names),):
        return f"dV shape {dV.shape}"
    if not np.all(np.isfinite(dV)):
        bad = [arm_names[i] for i in np.flatnonzero(~np.isfinite(dV))]
        return "nan:" + ",".join(bad)
    pressures = getattr(m, "pressures_Pa", None)
    if pressures is not None:
        bad = [k for k, v in pressures.items() if not np.isfinite(float(v))]
        if bad:
            return "nan:" + ",".join(bad)
    elif not np.isfinite(float(m.p_urethra)):
        return "nan:urethra"
    if not np.isfinite(float(m.t)):
        return "nan:t"
    return ""


def measured_pressures(m, names: tuple[str, ...]) -> np.ndarray:
    """(M,) Pa: the measured gauge pressures of the internal cavities ``names`` in a sample —
    its ``pressures_Pa`` (name -> Pa) where it has them, else the BIP's ``p_urethra``."""
    given = getattr(m, "pressures_Pa", None)
    if given:
        missing = [n for n in names if n not in given]
        if missing:
            raise SolverError(f"the sample has no pressure of cavity {missing[0]} (has {', '.join(given)})")
        return np.array([float(given[n]) for n in names])
    if names == ("urethra",):
        return np.array([float(m.p_urethra)])
    if not names:
        return np.zeros(0)
    raise SolverError(f"the sample has only p_urethra; the model's internal cavities are {', '.join(names)}")


def repeat_last(last: Estimate, m, status: str, t0: float, skipped: int) -> Estimate:
    """An estimate for a sample that gave none (rejected, solver failure): the last state again,
    with the sample's time and volumes and ``status``."""
    t = float(m.t) if np.isfinite(float(m.t)) else last.t
    n = len(last.volume_meas)
    dV = np.asarray(m.dV, float).copy() if np.shape(m.dV) == (n,) else np.full(n, np.nan)
    return Estimate(
        t=t, force=last.force.copy(), p_urethra=last.p_urethra, pose=last.pose,
        target_shift=dict(last.target_shift), volume_pred=last.volume_pred.copy(), volume_meas=dV,
        cond_W=last.cond_W, qp_status=status, step_time=time.perf_counter() - t0, skipped=int(skipped),
        status=status, in_envelope=last.in_envelope, pressures_Pa=last.pressures_Pa, layout=last.layout,
    )


def sensitivity_cond(W: np.ndarray) -> float:
    """Condition number of the force columns of an (n_arms, 3 + M) sensitivity (inf if rank-deficient)."""
    s = np.linalg.svd(np.asarray(W)[:, :3], compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def rest_estimate(target_names, W: np.ndarray, layout: ChannelLayout,
                  pressure_names: tuple[str, ...] | None = None) -> Estimate:
    """The estimate before the first sample of a phantom of ``layout``: no load, no motion,
    ``cond_W`` of the sensitivity ``W``; ``pressure_names`` the pressures it reports (default:
    the layout's actuated cavities)."""
    z = np.zeros(3)
    names = layout.actuated if pressure_names is None else tuple(pressure_names)
    pressures = None if names == ("urethra",) else dict.fromkeys(names, 0.0)
    return Estimate(
        t=0.0, force=z.copy(), p_urethra=0.0, pose=Pose6(z.copy(), z.copy()),
        target_shift={k: z.copy() for k in target_names}, volume_pred=np.zeros(len(W)),
        volume_meas=np.zeros(len(W)), cond_W=sensitivity_cond(W), qp_status="rest", step_time=0.0,
        pressures_Pa=pressures, layout=layout,
    )


class EstimatorState:
    """What every estimator shares around its state ``_lam`` / ``_last``: the ``with`` protocol
    (calls ``close``) and the read-only accessors."""

    _lam: np.ndarray
    _last: Estimate

    def close(self) -> None:  # overridden where something runs in the background
        """Stop anything running in the background (nothing here)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def lam(self) -> np.ndarray:
        """(3 + M,) the current actuation estimate: force N (3), the internal cavities' pressures Pa."""
        return self._lam.copy()

    @property
    def last(self) -> Estimate:
        """The latest estimate (the rest estimate before the first step)."""
        return self._last


class _Worker(threading.Thread):
    """Background equilibrium: solves at the newest requested λ, publishes linearizations."""

    def __init__(self, est: "Estimator") -> None:
        super().__init__(name="softphantom-equilibrium", daemon=True)
        self._est = est
        self._cond = threading.Condition()
        self._req: np.ndarray | None = None
        self._halt = False
        self.busy = False
        self.error: str | None = None

    def request(self, lam: np.ndarray) -> None:
        with self._cond:
            self._req = lam
            self._cond.notify_all()  # idle() waits on the same condition

    def stop(self) -> None:
        with self._cond:
            self._halt = True
            self._cond.notify_all()
        self.join()

    def run(self) -> None:
        est = self._est
        while True:
            with self._cond:
                while self._req is None and not self._halt:
                    self._cond.wait()
                if self._halt:
                    return
                lam, self._req = self._req, None
                self.busy = True
            try:
                with est._lock:
                    lin, path = est._lin, est._path
                if est._moved(lam, lin):
                    est._refresh(lin, lam, path)
            except Exception as exc:  # kept for the foreground; the thread goes on
                self.error = f"{type(exc).__name__}: {exc}"
            finally:
                with self._cond:
                    self.busy = self._req is not None
                    self._cond.notify_all()

    def idle(self, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        with self._cond:
            while self.busy or self._req is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True


class Estimator(EstimatorState):
    """Force, urethra pressure, pose, deformation and target shifts from the arm-cavity volumes.

    ``Estimator(model, config)``: ``model`` a :class:`~softphantom.design.PhantomModel`. Building
    it factors the tangent once (rest linearization, :attr:`rest`). :meth:`step` turns a
    :class:`~softphantom.sensing.Measurement` into an :class:`~softphantom.estimation.Estimate`;
    a bad sample (status not ok, NaN) gives an Estimate with ``status="rejected:<why>"`` that
    repeats the last state, which stays untouched. :meth:`node_positions` (N,3) m on demand.
    In async mode call :meth:`close` (or use ``with``) to stop the background thread.
    """

    kind = "refresh"

    def __init__(self, model, config: EstimatorConfig | None = None) -> None:
        self.config = cfg = config or EstimatorConfig()
        self.model = model
        self.forward = fwd = ForwardModel(model, cfg)
        self.fem = fwd.fem
        self.layout = fwd.layout  # the rows of V and W (sensing), the loads λ[3:] (actuated)
        self.arm_names = self.layout.sensing
        self.pressure_names = self.layout.actuated
        self.contact_point = fwd.contact_point
        self.marker_names, self.target_names = fwd.marker_names, fwd.target_names
        self._eq = fwd.eq
        self._nm = fwd.n_markers
        self.rest: Linearization = fwd.rest
        self.rest_markers = self.rest.sub_x[: self._nm].copy()
        self.rest_targets = self.rest.sub_x[self._nm:].copy()
        self._lo = np.array(cfg.force_min_N)
        self._hi = np.array(cfg.force_max_N)
        self._lock = threading.Lock()
        self._worker: _Worker | None = None
        self._init_state()

    # -- state ------------------------------------------------------------------------------------
    def _init_state(self) -> None:
        self._lin = self.rest
        self._path = None  # PathCorrection from the previous linearization to the current one
        self._trust_scale = self.config.trust_start_scale
        self._lam = np.zeros(self._eq.n_loads)
        self._since_refresh = 0
        self.refreshes = 0
        # per-refresh history, the latest HISTORY entries only: a soak must not grow the process
        self.lin_errors = History(width=len(self.arm_names))
        self.refresh_times = History()  # s per equilibrium refresh (both modes)
        self._last = rest_estimate(self.target_names, self.rest.W, self.layout)
        if self.config.mode == "async" and self._worker is None:
            self._worker = _Worker(self)
            self._worker.start()

    def reset(self) -> None:
        """Back to rest (λ = 0, the rest linearization); the background thread is restarted."""
        self.close()
        self._init_state()

    def close(self) -> None:
        """Stop the background thread (async mode); idempotent."""
        if self._worker is not None:
            self._worker.stop()
            self._worker = None

    @property
    def linearization(self) -> Linearization:
        """The linearization the next step will use."""
        return self._lin

    def _refresh(self, lin: Linearization, lam: np.ndarray, path: "PathCorrection | None") -> None:
        """The one equilibrium refresh (step in sync mode, the worker, settle): solve at ``lam``
        from ``lin``, time it, publish the new linearization."""
        t0 = time.perf_counter()
        new = self._eq.solve(lin, lam, path)
        self.refresh_times.append(time.perf_counter() - t0)
        self._publish(new)

    def _publish(self, lin: Linearization) -> None:
        prev = self._lin
        path = PathCorrection.between(prev, lin) if self.config.path_correction else None
        # adaptive trust region: grow it while the refreshes show the first-order map to be good
        # over the step taken, shrink it (not below the configured radius) where it was not
        dV = float(np.linalg.norm(lin.V - prev.V))
        err = float(np.linalg.norm(lin.lin_error))
        if np.isfinite(err) and dV > 0:
            ratio = err / dV
            if ratio < TRUST_GROW_BELOW and not lin.refactored:
                self._trust_scale = min(self._trust_scale * 2.0, self.config.trust_max_scale)
            elif ratio > TRUST_SHRINK_ABOVE or lin.refactored:
                self._trust_scale = max(self._trust_scale * 0.5, 1.0)
        with self._lock:
            self._lin = lin
            self._path = path
            self.refreshes += 1
            self.lin_errors.append(np.asarray(lin.lin_error))

    def _moved(self, lam: np.ndarray, lin: Linearization) -> bool:
        c = self.config
        return bool(np.max(np.abs(lam[:3] - lin.lam[:3])) > c.deadband_N
                    or np.max(np.abs(lam[3:] - lin.lam[3:]), initial=0.0) > c.deadband_Pa)

    def _target(self, lam: np.ndarray, lin: Linearization) -> np.ndarray:
        """Where the next equilibrium is solved: the estimate, at most ``trust_N`` / ``trust_Pa``
        away from the linearization point (a trust region: Gauss–Newton on this strongly
        non-linear map can jump into another basin from a far-off linearization)."""
        c = self.config
        k = self._trust_scale
        d = lam - lin.lam
        d[:3] = np.clip(d[:3], -k * c.trust_N, k * c.trust_N)
        d[3:] = np.clip(d[3:], -k * c.trust_Pa, k * c.trust_Pa)
        return lin.lam + d

    def node_positions(self) -> np.ndarray:
        """(N,3) m node positions of the current estimate (first order about the linearization)."""
        lin = self._lin
        return lin.predict_nodes(self._lam)

    # -- the estimate -----------------------------------------------------------------------------
    def _estimate(self, m, lin: Linearization, skipped: int, t0: float,
                  path: "PathCorrection | None" = None) -> tuple[Estimate, np.ndarray]:
        dV = np.asarray(m.dV, float)
        p = measured_pressures(m, self.pressure_names)
        dp = p - lin.lam[3:]
        if path is not None and path.lin is not lin:
            path = None
        W, s = lin.W, 0.0
        for _ in range(PATH_ITERATIONS if path is not None else 1):
            qp = solve_volume_qp(W, lin.V - dV, dp, self._lo - lin.lam[:3], self._hi - lin.lam[:3],
                                 self.config.qp_solver)
            if qp.status != "optimal":
                raise SolverError(f"QP {qp.status}")
            if path is None:
                break
            s_new = path.position(qp.dlam)
            if abs(s_new - s) <= 1e-3:
                break
            s = s_new
            W = path.W(s)
        lam = lin.lam + qp.dlam
        lam[:3] = np.clip(lam[:3], self._lo, self._hi)  # round-off of the active set
        lam[3:] = p
        if path is None:
            pts, vpred = lin.predict_points(lam), lin.predict_volumes(lam)
        else:
            pts, vpred = path.predict_points(lam), path.predict_volumes(lam)
        pose, shifts = pose_and_shifts(self.rest_markers, self.rest_targets, self.target_names, pts)
        est = Estimate(
            t=float(m.t), force=lam[:3].copy(), p_urethra=self._p_urethra(lam), pose=pose, target_shift=shifts,
            volume_pred=vpred, volume_meas=dV.copy(), cond_W=sensitivity_cond(lin.W),
            qp_status=qp.status, step_time=time.perf_counter() - t0, skipped=int(skipped),
            extra={"qp_residual_m3": qp.residual, "active": qp.active, "lin_lam": lin.lam,
                   **({} if self.pressure_names == ("urethra",) else
                      {"pressures_Pa": dict(zip(self.pressure_names, lam[3:].tolist()))})},
            layout=self.layout,
        )
        return est, lam

    def _p_urethra(self, lam: np.ndarray) -> float:
        """The estimate's ``p_urethra``: the urethra's pressure (NaN for a model without one)."""
        names = self.pressure_names
        return float(lam[3 + names.index("urethra")]) if "urethra" in names else float("nan")

    def step(self, m, skipped: int = 0) -> Estimate:
        """Estimate the state for one measurement (see the class docstring)."""
        t0 = time.perf_counter()
        why = check_sample(m, self.arm_names)
        if why:
            return repeat_last(self._last, m, f"rejected:{why}", t0, skipped)
        with self._lock:
            lin, path = self._lin, self._path
        try:
            est, lam = self._estimate(m, lin, skipped, t0, path)
            if self.config.mode == "sync":
                self._since_refresh += 1
                moved = lam - lin.lam
                due = (np.max(np.abs(moved[:3])) > self.config.relinearize_N
                       or np.max(np.abs(moved[3:]), initial=0.0) > self.config.relinearize_Pa
                       or self._since_refresh >= self.config.refresh_every)
                if due and self._moved(lam, lin):
                    self._refresh(lin, self._target(lam, lin), self._path)
                    self._since_refresh = 0
                    est, lam = self._estimate(m, self._lin, skipped, t0, self._path)
            elif self._worker is not None:
                self._worker.request(self._target(lam, lin))
        except SolverError as exc:
            return repeat_last(self._last, m, f"failed:{exc}", t0, skipped)
        self._lam = lam
        self._last = est
        return est

    def settle(self, m, max_refreshes: int = 30, tol_N: float = 1e-7, tol_Pa: float = 1e-3,
               timeout_s: float = 120.0) -> Estimate:
        """Hold the measurement ``m`` until the equilibrium has converged on it (a steady input):
        step, re-linearize at the estimate, repeat until the estimate is within ``tol_N`` /
        ``tol_Pa`` of the linearization point (a Gauss–Newton fixed point). Returns the last
        estimate. In async mode the background thread does the refreshes."""
        for _ in range(max_refreshes + 1):
            if self._worker is not None:
                self._worker.idle(timeout_s)
            lin = self._lin
            est = self.step(m)  # in async mode this also asks the worker for the next refresh
            if est.status != "ok":
                return est
            lam = self._lam
            if (np.max(np.abs(lam[:3] - lin.lam[:3])) <= max(tol_N, self.config.deadband_N)
                    and np.max(np.abs(lam[3:] - lin.lam[3:]), initial=0.0) <= max(tol_Pa, self.config.deadband_Pa)):
                return est
            if self._worker is not None:
                self._worker.idle(timeout_s)
                if self._lin is lin:
                    raise SolverError(f"background equilibrium did not refresh: {self._worker.error}")
            else:
                self._refresh(lin, self._target(lam, lin), None)
        return est

    # -- noise ------------------------------------------------------------------------------------
    def noise_bound(self, sigma_dV_m3, sigma_p_Pa: float = 0.0) -> NoiseBound:
        """1-σ errors from independent volume noise ``sigma_dV_m3`` (scalar or (n_arms,)) and urethra
        pressure noise at the current linearization and estimate (:func:`noise_bound`)."""
        return noise_bound(self._lin, self.rest_markers, self.target_names, sigma_dV_m3, sigma_p_Pa, self._lam)

    def stats(self) -> dict:
        """Counters: refreshes, factorizations, the largest linearization error (m³) of the latest
        :data:`HISTORY` refreshes, worker error."""
        errs = self.lin_errors.values()
        return {
            "refreshes": self.refreshes,
            "factorizations": self._eq.factorizations,
            "max_lin_error_m3": float(np.nanmax(np.abs(errs))) if errs.size else 0.0,
            "worker_error": None if self._worker is None else self._worker.error,
        }
