"""``softphantom calibrate`` end to end: sessions → keyframes → initial guess → least squares on
Dask → held-out check → a calibrated model directory and a report."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softphantom.calibration.fit import FitOptions, FitResult, Keyframes, Problem, body_pose, fit, parameter_set
from softphantom.calibration.forward import GROUPS, design_with_law, rest_markers, solve_keyframe, group_shapes
from softphantom.calibration.tube import combine, fit_tube_tau
from softphantom.calibration.session import CalibrationInputError, Session, load_session, select_keyframes
from softphantom.errors import SolverError, UserError
from softphantom.sensing.pneumatics import boyle_dV
from softphantom.records.names import POSE_COLUMNS as POSE_DOF

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionSpec:
    """One trial to read: ``recording``, ``truth`` (take), ``contact`` (a ``p_ext`` name of the
    model or (x, y, z) m), ``known_loads`` (CSV or None)."""

    recording: Path
    truth: Path
    contact: str | tuple[float, float, float] = "on-centre"
    known_loads: Path | None = None


@dataclass(frozen=True, eq=False)
class HeldOut:
    """Pose errors (K, 6) in mm and degrees at keyframes, forces inferred from the pressures alone,
    with the nominal and the calibrated parameters; force errors (K, 3) N where the session has
    known loads (NaN elsewhere); per-DoF RMSE of each."""

    names: tuple[str, ...]
    t: np.ndarray
    err_nominal: np.ndarray
    err_calibrated: np.ndarray
    force_err_nominal: np.ndarray
    force_err_calibrated: np.ndarray

    def rmse(self, which: str) -> np.ndarray:
        e = self.err_nominal if which == "nominal" else self.err_calibrated
        return np.sqrt(np.nanmean(e**2, axis=0))

    def force_rmse(self, which: str) -> float:
        """RMS of the force error (N, all components), NaN without known loads."""
        e = self.force_err_nominal if which == "nominal" else self.force_err_calibrated
        return float(np.sqrt(np.nanmean(e**2))) if np.isfinite(e).any() else float("nan")


@dataclass(frozen=True, eq=False)
class Calibration:
    """Everything ``calibrate`` found: the fit, the keyframes, the held-out checks on the fitting
    data (``fitting``) and on the held-out sessions (``held_out``, None without them)."""

    model_dir: Path
    fit: FitResult
    frames: Keyframes
    sessions: list[Session]
    fitting: HeldOut
    held_out: HeldOut | None
    options: FitOptions
    meta: dict = field(default_factory=dict)

    def parameters(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.fit.names, self.fit.value)}


def _contact(model, c) -> tuple[float, float, float]:
    if isinstance(c, str):
        if c not in model.p_ext:
            raise UserError(f"--contact {c!r}: not a contact point of the model (have {', '.join(model.p_ext)}, or X,Y,Z_mm)")
        return tuple(float(v) for v in model.p_ext[c])
    return tuple(float(v) for v in c)


def _load_sessions(model, specs: list[SessionSpec], prefix: str) -> list[Session]:
    """The sessions of ``specs``, each recording's channels the model's (its arms, and the pressure
    of every internal cavity, in the model's load order); a take that does not overlap its
    recording is refused here, before any cluster starts (:func:`_lag_grid`)."""
    out = [load_session(sp.recording, sp.truth, _contact(model, sp.contact), sp.known_loads, name=f"{prefix}{i + 1}",
                        layout=model.layout)
           for i, sp in enumerate(specs)]
    for se in out:
        _lag_grid(se)
    return out


def _solver(client) -> Callable[[list[tuple]], list]:
    if client is None:
        return lambda tasks: [solve_keyframe(*t) for t in tasks]
    from softphantom.parallel import map_tasks

    def run(tasks):
        out = map_tasks(client, solve_keyframe, tasks, label=None)  # a round of the fit: its lines say enough
        bad = [r for r in out if not r.ok]
        if bad:
            raise SolverError(f"forward solve of keyframe {bad[0].index}: {bad[0].error}")
        return [r.value for r in out]

    return run


def _lag_grid(se: Session) -> tuple[np.ndarray, float]:
    """The recording's clock on which the take is aligned (s, every 20 ms) and the half-width of
    the lag search (s); refuses a take that does not overlap the recording in time."""
    grid = np.arange(se.t[0], se.t[-1], 0.02)
    overlap = min(se.truth_t[-1], grid[-1]) - max(se.truth_t[0], grid[0])
    search = min(2.0, 0.45 * max(overlap, 0.0))
    if search <= 0.05:
        raise CalibrationInputError(
            f"session {se.name}: the take ({se.truth_t[0]:.2f}–{se.truth_t[-1]:.2f} s) does not overlap the "
            f"recording ({se.t[0]:.2f}–{se.t[-1]:.2f} s) in time")
    return grid, search


def _initial(problem: Problem, sessions: list[Session]) -> tuple[np.ndarray, np.ndarray]:
    """First guess of the keyframe forces and of each session's clock lag from the nominal model
    linearized at rest: force = least squares of the pressures' volumes; lag by cross-correlating
    the linear model's pose with the take."""
    from softphantom.tracking.timing import estimate_lag

    fr = problem.frames
    contacts = sorted({tuple(c) for c in fr.contact})
    zero = {gr: 1.0 for gr in GROUPS}
    rest = problem.solve_many([(problem.model_dir, c, problem.options.radius_m, zero, np.zeros(3), 0.0, None,
                                1.0 / 1024, None, 1e-9, problem.options.law) for c in contacts])
    lin = dict(zip(contacts, rest))
    forces = np.zeros((len(fr), 3))
    lags = np.zeros(len(sessions))
    rm = problem.rest_markers
    for i, se in enumerate(sessions):
        vt = se.tube_m3
        s0 = lin[tuple(se.contact)]
        pinv = np.linalg.pinv(s0.dV_df)

        def force_of(dp):
            return (pinv @ boyle_dV(dp.T, (se.cavity_m3 + vt)[:, None], se.p0_Pa)).T

        sel = fr.session == i
        forces[sel] = force_of(fr.dp[sel])
        # linear pose prediction on the recording's clock
        grid, search = _lag_grid(se)
        dp = np.stack([np.interp(grid, se.t, se.dp[:, k]) for k in range(se.dp.shape[1])], axis=1)
        f = force_of(dp)
        M = rm[None] + np.einsum("kij,nj->nki", s0.dM_df, f)
        pred = np.array([body_pose(rm, m, np.zeros(3), np.zeros(3)) for m in M])
        try:
            res = estimate_lag(se.truth_t, se.truth_pose[:, :3] * 1e3, grid, pred[:, :3] * 1e3, max_lag_s=search)
        except ValueError as exc:
            raise CalibrationInputError(f"session {se.name}: cannot align the take with the recording ({exc})") from None
        lags[i] = -res.lag_s  # take time = recording time + lag
    known = np.all(np.isfinite(fr.known), axis=1)
    forces[known] = fr.known[known]
    return forces, lags


def _pose_errors(problem: Problem, g: np.ndarray, forces0: np.ndarray, what: str = "",
                 nominal: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(K, 6) mm/deg: pose from forces fitted to the pressures alone (all globals held at ``g``)
    minus the take; (K, 3) N those forces minus the known loads (NaN where none). Logs one line
    with the solves and seconds it took, naming it ``what``. ``nominal``: the model as
    designed, under the design's law whatever law the fit used (``FitOptions.law``)."""
    names = problem.names()
    u = problem.unpack(g)
    law = None if nominal else problem.options.law
    p = dataclasses.replace(problem, options=dataclasses.replace(problem.options, fix=tuple(names) + ("lag", "drift"),
                                                                  max_iter=8, law=law),
                            use_pose=False, use_known=False, x_warm=list(problem.x_warm), solves=0,
                            lag0_s=u["lag"].copy(), drift0=u["drift"].copy(),
                            params=tuple(dataclasses.replace(pp, nominal=float(v))
                                         for pp, v in zip(problem.params, g)))
    res = fit(p, forces0, level=logging.DEBUG)
    log.info(f"pose check, {what}: {res.solves} forward solves, {len(res.history) - 1} iterations, {res.seconds:.0f} s")
    u = p.unpack(res.z[:p.n_global])
    fr = p.frames
    err = np.full((len(fr), 6), np.nan)
    for k, s in enumerate(res.solutions):
        se = p.sessions[int(fr.session[k])]
        meas = se.pose_at(fr.t[k] + u["lag"][int(fr.session[k])])[0]
        pred = body_pose(p.rest_markers, s.markers, u["rho"], u["pivot"])
        d = pred - meas
        d[3:] = (d[3:] + np.pi) % (2 * np.pi) - np.pi
        err[k] = np.concatenate([d[:3] * 1e3, np.degrees(d[3:])])
    return err, res.forces - fr.known


def _pair(nominal, calibrated):
    return nominal[0], calibrated[0], nominal[1], calibrated[1]


def calibrate(model_dir, specs: list[SessionSpec], holdout: list[SessionSpec] = (), *,
              options: FitOptions = FitOptions(), scheduler: str | None = None, n_workers: int | None = None,
              in_process: bool = False, max_keyframes: int = 16) -> Calibration:
    """Fit the model in ``model_dir`` to the sessions ``specs``; check on ``holdout`` sessions.

    Forward solves run on Dask (a local cluster unless ``scheduler`` is an address), or in this
    process with ``in_process``. Logs one line per stage and iteration."""
    from softphantom.design import load_model
    from softphantom.parallel import dask_client

    model_dir = Path(model_dir)
    model = load_model(model_dir)
    if not specs:
        raise UserError("calibrate: give at least one --recording/--truth pair")
    design_laws = sorted({m.law for m in model.design.materials})
    fitted = dataclasses.replace(model, design=design_with_law(model.design, options.law))
    if options.law is not None and design_laws != [options.law]:
        log.info(f"fitting under the {options.law} law (the design's: {', '.join(design_laws)}), every material at its "
            "small-strain E and ν; the nominal checks use the design's law")

    sessions = _load_sessions(model, specs, "s")
    held = _load_sessions(model, holdout, "h")
    times = [select_keyframes(se, max_keyframes) for se in sessions]
    frames = Keyframes.of(sessions, times)
    log.info(f"{len(sessions)} session(s), {len(frames)} keyframes"
        + (f", {int(np.all(np.isfinite(frames.known), axis=1).sum())} with known loads" if np.isfinite(frames.known).any() else ""))
    if not np.isfinite(frames.known).any() and "stiffness_bulb_factor" not in options.fix:
        log.info("no known loads: the stiffness and the force scale are confounded; the fit reports it")
    tube = combine([fit_tube_tau(se) for se in sessions])
    tube_meta = {} if tube is None else {"tube_tau": {
        "tau_ms": [round(float(v) * 1e3, 3) for v in tube.tau_s], "sd_ms": [round(float(v) * 1e3, 3) for v in tube.sd_s],
        "nominal_ms": [round(float(v) * 1e3, 3) for v in tube.nominal_s], "sessions": tube.session}}
    log.info("tube τ: " + ("held at the tube's (no session with known loads)" if tube is None else
                           ", ".join(f"{a} {v * 1e3:.1f} ± {s * 1e3:.1f} ms (tube {n * 1e3:.1f})" for a, v, s, n in
                                     zip(fitted.design.sensing_names, tube.tau_s, tube.sd_s, tube.nominal_s))))

    ctx = nullcontext(None) if in_process else dask_client(scheduler, n_workers)
    with ctx as client:
        solve_many = _solver(client)
        rm = rest_markers(str(model_dir), tuple(frames.contact[0]), options.radius_m)
        params = parameter_set(measured=options.measured, shapes=group_shapes(fitted),
                               arm_names=fitted.design.sensing_names)
        problem = Problem(str(model_dir), sessions, frames, rm, solve_many, options, params)
        forces0, lags0 = _initial(problem, sessions)
        problem = dataclasses.replace(problem, lag0_s=lags0, pose_rows=None)
        log.info("lag (take − recording): " + ", ".join(f"{se.name} {lg * 1e3:+.1f} ms" for se, lg in zip(sessions, lags0)))
        result = fit(problem, forces0)
        log.info(f"fit: {result.solves} forward solves, {result.seconds:.0f} s")
        g_cal = result.z[:problem.n_global]
        g_nom = problem.nominal()
        fitting = HeldOut(POSE_DOF, frames.t, *_pair(_pose_errors(problem, g_nom, forces0, "fitting data, nominal", True),
                                                       _pose_errors(problem, g_cal, result.forces,
                                                                    "fitting data, calibrated")))
        held_out = _held_out(str(model_dir), held, rm, solve_many, options, params, g_cal[:len(params)],
                             max_keyframes) if held else None
    return Calibration(model_dir, result, frames, sessions, fitting, held_out, options,
                       meta={**tube_meta, "law": {"design": design_laws, "fitted": sorted({m.law for m in fitted.design.materials})},
                             "sessions": [f"s{i + 1}: {s.recording}" for i, s in enumerate(specs)],
                             "held_out": [f"h{i + 1}: {s.recording}" for i, s in enumerate(holdout)]})


def held_out_lag(session: Session, lag_s: float, tube: float) -> float:
    """The lag (take − recording, s) of a held-out session for pressures de-lagged with the time
    constant of a tube ``tube`` × the recording's. ``lag_s`` was found by cross-correlation
    (:func:`_initial`) on the pressures de-lagged with the recording's τ; with ``tube`` > 1 those
    are late by τ(tube) − τ(1) (p + Δτ·ṗ ≈ p(t + Δτ)), and the correlation moved the lag to match.
    Keeping ``lag_s`` while the pressures come Δτ earlier (≈ 21 ms for a tube 10 % long) would give
    the calibrated check a ramp error of its own that the nominal does not have (a floor of
    0.038 mm/deg RMS on the benchmark's held-out needle with exact pressures and the truth's own
    parameters).

    >>> import numpy as np
    >>> se = Session("h1", np.zeros(2), np.zeros((2, 4)), np.zeros(2), np.zeros(2), np.zeros((2, 6)),
    ...              np.zeros(3), 101325.0, 12.0, 1.2e-3, np.full(4, 4.9e-7))
    >>> round(1e3 * (held_out_lag(se, -0.020, 1.1) + 0.020), 1)  # ms: τ(13.2 m) − τ(12 m)
    20.7
    """
    return float(lag_s + np.mean(session.tau_s(tube) - session.tau_s(1.0)))


def _held_out(model_dir: str, held: list[Session], rm, solve_many, options: FitOptions, params, g_params: np.ndarray,
              max_keyframes: int) -> HeldOut:
    """Pose errors on held-out sessions with the nominal and with the parameters ``g_params``."""
    htimes = [select_keyframes(se, max_keyframes) for se in held]
    hframes = Keyframes.of(held, htimes)
    hp = Problem(model_dir, held, hframes, rm, solve_many, options, params)
    f0, hl = _initial(hp, held)
    gl = len(hp.params)
    # a held-out session's drift is its own, unknown to the calibration (as to the estimator): 0
    rest = np.concatenate([hl, np.zeros(len(held))])
    gn = np.concatenate([hp.nominal()[:gl], rest])
    gc = np.concatenate([np.asarray(g_params, float), rest])
    tube = hp.unpack(gc)["tube"]
    gc[gl:gl + len(held)] = [held_out_lag(se, lg, tube) for se, lg in zip(held, hl)]
    hp = dataclasses.replace(hp, lag0_s=hl, pose_rows=None)
    return HeldOut(POSE_DOF, hframes.t, *_pair(_pose_errors(hp, gn, f0, "held-out, nominal", True),
                                               _pose_errors(hp, gc, f0, "held-out, calibrated")))


def check_held_out(model_dir, holdout: list[SessionSpec], values: dict[str, float], *,
                   options: FitOptions = FitOptions(), scheduler: str | None = None, n_workers: int | None = None,
                   in_process: bool = False, max_keyframes: int = 16) -> HeldOut:
    """The held-out check of :func:`calibrate` alone, for parameters fitted before (``values``: by
    name in displayed units, as ``Calibration.parameters()``; names missing keep their nominal; lags
    and drifts are ignored, each held-out session gets its own): on new held-out sessions, without
    fitting again."""
    from softphantom.design import load_model
    from softphantom.parallel import dask_client

    model = load_model(Path(model_dir))
    fitted = dataclasses.replace(model, design=design_with_law(model.design, options.law))
    held = _load_sessions(model, holdout, "h")
    params = parameter_set(measured=options.measured, shapes=group_shapes(fitted),
                               arm_names=fitted.design.sensing_names)
    values = {n: v for n, v in values.items() if not n.startswith(("lag_", "drift_"))}
    unknown = sorted(set(values) - {p.name for p in params})
    if unknown:
        raise UserError(f"check_held_out: parameters not in this model's set: {', '.join(unknown)}")
    g = np.array([p.internal(values[p.name]) if p.name in values else p.nominal for p in params])
    with nullcontext(None) if in_process else dask_client(scheduler, n_workers) as client:
        rm = rest_markers(str(model_dir), _contact(model, holdout[0].contact), options.radius_m)
        return _held_out(str(model_dir), held, rm, _solver(client), options, params, g, max_keyframes)


def rmse_ratio(held: HeldOut) -> float:
    """Nominal over calibrated pose RMSE (all six DoF, mm and degrees together)."""
    a = np.sqrt(np.nanmean(held.err_nominal**2))
    b = np.sqrt(np.nanmean(held.err_calibrated**2))
    return float(a / b) if b > 0 else math.inf


def rmse_ratio_interval(held: HeldOut, level: float = 0.9, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    """The spread of :func:`rmse_ratio` over which keyframes happened to be held out: its
    ``level`` percentile interval over ``n`` bootstrap resamples of the keyframes (with
    replacement, a keyframe's six DoF together). A held-out session of few keyframes (the needle
    insertion gives 7) and a small nominal error make the ratio hang on one or two of them; this
    says how much."""
    en, ec = np.asarray(held.err_nominal, float), np.asarray(held.err_calibrated, float)
    rows = np.flatnonzero(np.isfinite(en).any(axis=1) & np.isfinite(ec).any(axis=1))
    if rows.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    pick = rows[rng.integers(0, rows.size, (n, rows.size))]
    a = np.sqrt(np.nanmean(en[pick] ** 2, axis=(1, 2)))
    b = np.sqrt(np.nanmean(ec[pick] ** 2, axis=(1, 2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(b > 0, a / b, np.inf)
    q = (1.0 - level) / 2.0
    return float(np.quantile(r, q)), float(np.quantile(r, 1.0 - q))
