"""The atlas's reduced-order offline stage (``AtlasConfig.offline = "rom"``, docs/offline.md).

Instead of one converged full solve per grid point, the grid is solved by a hyper-reduced model
(:mod:`softphantom.fem.rom`) trained on a few full solves:

1. **snapshots** (:func:`snapshot_loads`, on Dask): full solves at the envelope box's 16 corners,
   seeded Latin-hypercube loads, and (where f_x spans 0) loads along f_x through the arm pair's
   step at the top of the f_y range; each with its exact load sensitivities K⁻¹B;
2. **training**: POD of the states and the sensitivities (scaled by the box's half-widths), then the
   ECSW element set and weights (:func:`~softphantom.fem.rom.ecsw_weights`);
3. **grid**: every grid point a reduced Newton solve from its neighbour's reduced state (a
   displacement axis: the faces force-controlled, the points between under mixed control, f_x the
   unknown that puts the patch displacement on the node);
4. **checks** (on Dask): full solves at seeded grid points started from the reduced states; the
   largest differences (volumes, tracked points, f_x) are the build's measured error, kept in the
   atlas's provenance (``softphantom atlas info``). If they exceed :data:`CHECK_DV_MM3`, the check
   solves join the snapshots and the model is trained and the grid solved again (at most
   :data:`MAX_ROUNDS` rounds), each round checked at new points.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.estimation.atlas.config import FALLBACK_MIN_LOAD_STEP, VIA_TOL, x_patch
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.linearization import Linearization, PatchControl
from softphantom.fem.rom import ReducedModel, ecsw_weights, pod_basis

N_LHS = 24  # seeded Latin-hypercube snapshot loads (besides the 16 corners and the step's lines)
STEP_FX_N = (0.01, 0.03, 0.1, 0.3)  # |f_x| of the snapshots along f_x through the arm pair's step
N_CHAINS = 4  # snapshot tasks (each a walk from rest through its loads)
POD_RTOL = 1e-12  # dropped energy of the basis (of states and scaled sensitivities)
ECSW_TOL = 1e-3  # relative error of the hyper-reduced force at the training states
N_CHECK = 8  # full-solve checks per round
CHECK_DV_MM3 = 0.05  # a round whose checks miss the volumes by more trains again with them
MAX_ROUNDS = 2
SEED = 7
SNAPSHOT_CACHE = None  # a path: the snapshot solves kept there and reused (benchmarks re-running one build)

log = logging.getLogger(__name__)


def snapshot_loads(lower: np.ndarray, upper: np.ndarray, n_lhs: int | None = None, seed: int = SEED) -> np.ndarray:
    """(n, 4) N, N, N, Pa: the snapshot loads in the box [lower, upper] (see the module docstring).

    >>> import numpy as np
    >>> L = snapshot_loads(np.array([-2, -1, -2, -2e3]), np.array([2, 5, 2, 40e3]), n_lhs=4)
    >>> L.shape, bool(((L >= [-2, -1, -2, -2e3]) & (L <= [2, 5, 2, 40e3])).all())
    ((36, 4), True)
    """
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    n_lhs = N_LHS if n_lhs is None else n_lhs
    rng = np.random.default_rng(seed)
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * 4, indexing="ij")).reshape(4, -1).T
    u = (rng.permuted(np.tile(np.arange(n_lhs), (4, 1)), axis=1).T + rng.uniform(size=(n_lhs, 4))) / max(n_lhs, 1)
    loads = [lo + (hi - lo) * corners, lo + (hi - lo) * u]
    if lo[0] < 0 < hi[0]:
        fz = float(np.clip(0.0, lo[2], hi[2]))
        p = 0.5 * (lo[3] + hi[3])
        for fy in (hi[1], lo[1] + 0.75 * (hi[1] - lo[1])):
            loads.append(np.array([[s * f, fy, fz, p] for f in STEP_FX_N for s in (-1, 1) if lo[0] < s * f < hi[0]]))
    return np.concatenate([a for a in loads if len(a)])


def _chains(loads: np.ndarray, scale: np.ndarray, n: int) -> list[np.ndarray]:
    """The loads in ``n`` walks: a nearest-neighbour tour from zero load, cut into ``n`` pieces."""
    left = list(range(len(loads)))
    at = np.zeros(4)
    order = []
    while left:
        d = [np.max(np.abs((loads[i] - at) / scale)) for i in left]
        i = left.pop(int(np.argmin(d)))
        order.append(i)
        at = loads[i]
    return [loads[c] for c in np.array_split(np.array(order), n) if len(c)]


def _start(fwd: ForwardModel, x: np.ndarray, lam: np.ndarray) -> Linearization:
    """A start for the full solver at a given state (no sensitivities: its predictor is the state)."""
    k, m = fwd.probe.shape[0], len(fwd.eq.arm_names)
    return Linearization(lam=lam, x=x, V=np.zeros(m), W=np.zeros((m, 4)), sub_x=np.zeros((k, 3)),
                         sub_U=np.zeros((k, 3, 4)), U=np.zeros((fwd.fem.n_dof, 4)), residual=np.nan)


def _snapshots(model, config: EstimatorConfig, loads: np.ndarray, scale: np.ndarray):
    """One task: full solves at ``loads`` in turn, each from the nearest one solved (from rest first),
    with the tangent factored at each solution (exact K⁻¹B). Returns (solved: list of (lam, x, U),
    first failure or '', CPU seconds, converged solves)."""
    t0 = time.process_time()
    fwd = ForwardModel(model, config, exact_sensitivities=False, fallback_min_load_step=FALLBACK_MIN_LOAD_STEP)
    done = [fwd.rest]
    out, err = [], ""
    for lam in loads:
        start = done[int(np.argmin([np.max(np.abs((lam - s.lam) / scale)) for s in done]))]
        try:
            lin = fwd.solve(lam, start, factor_at_solution=True, via_tol=VIA_TOL)
        except SolverError as exc:
            err = err or str(exc).splitlines()[0]
            continue
        done.append(lin)
        out.append((lin.lam.copy(), lin.x.copy(), lin.U.copy()))
    return out, err, time.process_time() - t0, len(out)


def _checks(model, config: EstimatorConfig, items):
    """One task: full solves at grid points started from their reduced states. ``items``: (lam, x,
    target_m or None (force control) , f_x bounds). Returns (list of (lam, x, U) or None per item,
    CPU seconds)."""
    t0 = time.process_time()
    fwd = ForwardModel(model, config, exact_sensitivities=False, fallback_min_load_step=FALLBACK_MIN_LOAD_STEP)
    h = x_patch(fwd)
    out = []
    for lam, x, target, bounds in items:
        control = None
        if target is not None:
            control = PatchControl(h=h, x_ref=fwd.fem.x_rest, target_m=target, tol_m=1e-9 * max(abs(target), 1e-6),
                                   fx_bounds_N=bounds)
        try:
            lin = fwd.eq.solve(_start(fwd, x, lam), lam, factor_at_solution=True, control=control)
        except SolverError:
            out.append(None)
            continue
        out.append((lin.lam.copy(), lin.x.copy(), lin.U.copy()))
    return out, time.process_time() - t0


def train(fwd: ForwardModel, snaps, lower: np.ndarray, upper: np.ndarray, *, pod_rtol: float = POD_RTOL,
          ecsw_tol: float = ECSW_TOL) -> tuple[ReducedModel, dict]:
    """The reduced model from snapshots ((lam, x, U) each): POD of the states and of the
    sensitivities scaled by the box's half-widths (the state change a load across the box makes),
    then the ECSW set. Returns (model, {"basis": r, "elements": |S|, "ecsw_error": ...})."""
    fem = fwd.fem
    half = 0.5 * (np.asarray(upper) - np.asarray(lower))
    cols = [fwd.rest.U * half] + [x[:, None] - fem.x_rest[:, None] for _, x, _ in snaps] + [U * half for *_, U in snaps]
    D = np.concatenate(cols, axis=1)[fem.free_dofs]
    Vf, _ = pod_basis(D, pod_rtol)
    V = np.zeros((fem.n_dof, Vf.shape[1]))
    V[fem.free_dofs] = Vf
    idx, w, err = ecsw_weights(fem, V, [x for _, x, _ in snaps], tol=ecsw_tol)
    if fwd.eq.pressure_names != ("urethra",):
        raise UserError(f"cavities: the reduced model takes one internal pressure, the urethra's; this design has "
                        f"{', '.join(fwd.eq.pressure_names) or 'none'}: use --estimator refresh")
    rom = ReducedModel(fem, V, fwd.H_f, fwd.eq._ur_tris, idx, w)
    return rom, {"basis": int(V.shape[1]), "elements": int(len(idx)), "ecsw_error": float(err)}


def _line_order(n: int, centre: int) -> list[int]:
    return [*range(centre, n), *range(centre - 1, -1, -1)]


def solve_grid(rom: ReducedModel, fwd: ForwardModel, acfg, h: np.ndarray | None = None):
    """Every grid point of ``acfg`` by the reduced model. Returns (Q (n1,n2,n3,n4,r) reduced states,
    F (n1,n2,n3,n4) f_x N, QN the first coordinates, solved, targets (n1,...) the patch
    displacement of each point under mixed control (NaN: force-controlled))."""
    ax = acfg.axes()
    shape = acfg.shape
    n1 = shape[0]
    Q = np.full((*shape, rom.r), np.nan)
    F = np.full(shape, np.nan)
    QN = np.broadcast_to(ax[0].reshape(-1, 1, 1, 1), shape).copy()
    T = np.full(shape, np.nan)
    solved = np.zeros(shape, bool)
    hr = rom.Hr[:, 0] if h is None else h
    disp = acfg.x_control == "displacement"
    faces = (0, n1 - 1) if disp else range(n1)
    c = [int(np.argmin(np.abs(a))) for a in ax]
    K = [None]  # the last reduced tangent: the next point's chord starts with it
    for l in _line_order(shape[3], c[3]):
        for k in _line_order(shape[2], c[2]):
            for j in _line_order(shape[1], c[1]):
                # the neighbour nearer the centre along the last axis that moved (solved before)
                prev = None
                for a, (v, cv) in enumerate(zip((j, k, l), c[1:])):
                    if v != cv:
                        prev = [j, k, l]
                        prev[a] += -1 if v > cv else 1
                        prev = tuple(prev)
                        break
                for i in faces:
                    lam = np.array([ax[0][i], ax[1][j], ax[2][k], ax[3][l]])
                    q0 = Q[(i, *prev)] if prev is not None and solved[(i, *prev)] else None
                    sol = _try(rom, lam, q0, K[0])
                    if sol is not None:
                        K[0] = sol.K
                        Q[i, j, k, l], F[i, j, k, l], solved[i, j, k, l] = sol.q, lam[0], True
                if not disp or not (solved[0, j, k, l] and solved[-1, j, k, l]):
                    continue
                u0, u1 = hr @ Q[0, j, k, l], hr @ Q[-1, j, k, l]
                q, fx = Q[0, j, k, l], ax[0][0]
                for i in range(1, n1 - 1):
                    target = u0 + (ax[0][i] - ax[0][0]) / (ax[0][-1] - ax[0][0]) * (u1 - u0)
                    lam = np.array([fx, ax[1][j], ax[2][k], ax[3][l]])
                    sol = _try(rom, lam, q, K[0], h=hr, target=target)
                    if sol is None:
                        break  # beyond a failed point on the line: unreachable
                    q, fx, K[0] = sol.q, sol.lam[0], sol.K
                    Q[i, j, k, l], F[i, j, k, l], T[i, j, k, l], solved[i, j, k, l] = q, fx, target, True
    return Q, F, QN, solved, T


def _try(rom: ReducedModel, lam, q0, K0, **kw):
    """The reduced solve at ``lam`` from ``q0`` (None: rest) with the tangent ``K0``, else from rest
    in load steps (force control only); None where neither converges."""
    try:
        return rom.solve(lam, q0, K0=K0 if q0 is not None else None, **kw)
    except SolverError:
        if kw:
            return None
    sol = None
    for s in (0.25, 0.5, 0.75, 1.0):
        try:
            sol = rom.solve(s * lam, None if sol is None else sol.q)
        except SolverError:
            return None
    return sol


def rom_grid(model, cfg: EstimatorConfig, acfg, fwd: ForwardModel, client):
    """The grid values of an atlas solved by the reduced model (see the module docstring): (V
    (n1..n4,4) m³, P (…,k,3) m, X (…,3N) m, solved, FX N, QN, full-solve CPU seconds, converged full
    solves, info for the provenance)."""
    from softphantom.parallel import map_tasks

    lo, hi = acfg.lower, acfg.upper
    ax = acfg.axes()
    scale = hi - lo
    shape = acfg.shape
    loads = snapshot_loads(lo, hi)
    t = time.perf_counter()
    cache = None
    if SNAPSHOT_CACHE is not None:
        import hashlib
        import pickle
        from pathlib import Path

        tag = hashlib.sha256(lo.tobytes() + hi.tobytes() + loads.tobytes()).hexdigest()[:12]
        cache = Path(f"{SNAPSHOT_CACHE}.{tag}.pkl")
    if cache is not None and cache.is_file():
        snaps, cpu_full, n_full, wall = pickle.loads(cache.read_bytes())
        t -= wall
    else:
        res = map_tasks(client, _snapshots, [(model, cfg, c, scale) for c in _chains(loads, scale, N_CHAINS)],
                        label=f"atlas (reduced): {len(loads)} snapshot solves")
        snaps, cpu_full, n_full = [], 0.0, 0
        for r in res:
            if not r.ok:
                raise SolverError(f"atlas: snapshot task failed: {r.error}")
            s, err, cpu, n = r.value
            snaps += s
            cpu_full += cpu
            n_full += n
            if err:
                log.info(f"atlas: {len(loads)} snapshot loads, a failure: {err}")
        if cache is not None:
            cache.write_bytes(pickle.dumps((snaps, cpu_full, n_full, time.perf_counter() - t)))
    log.info(f"atlas (reduced): {len(snaps)} snapshots, {cpu_full:.0f} CPU-s")
    if len(snaps) < 4:
        raise SolverError(f"atlas: only {len(snaps)} of {len(loads)} snapshot solves converged")
    info = {"offline": "rom", "snapshots": len(snaps), "snapshot_cpu_s": cpu_full,
            "snapshot_wall_s": time.perf_counter() - t, "rounds": []}
    rng = np.random.default_rng(SEED)
    for rnd in range(MAX_ROUNDS):
        t, c0 = time.perf_counter(), time.process_time()
        rom, tr = train(fwd, snaps, lo, hi)
        train_cpu = time.process_time() - c0
        t1, c1 = time.perf_counter(), time.process_time()
        Q, F, QN, solved, T = solve_grid(rom, fwd, acfg)
        grid_cpu, grid_wall = time.process_time() - c1, time.perf_counter() - t1
        pts = np.argwhere(solved)
        pick = pts[rng.choice(len(pts), size=min(N_CHECK, len(pts)), replace=False)]
        items = []
        for p in map(tuple, pick):
            lam = np.array([F[p], *[ax[a][p[a]] for a in (1, 2, 3)]])
            target = None if np.isnan(T[p]) else float(T[p])
            items.append((lam, rom.x(Q[p]), target, (lo[0], hi[0])))
        t2 = time.perf_counter()
        chunks = [items[i::2] for i in range(2)]
        res = map_tasks(client, _checks, [(model, cfg, c) for c in chunks if c],
                        label=f"atlas (reduced): {len(items)} check solves")
        checked, dV, dP, dF, check_cpu = [], [], [], [], 0.0
        for r, c in zip(res, [c for c in chunks if c]):
            if not r.ok:
                raise SolverError(f"atlas: check task failed: {r.error}")
            out, cpu = r.value
            check_cpu += cpu
            for (lam, x, _, _), full in zip(c, out):
                if full is None:
                    continue
                checked.append(full)
                xf = full[1]
                dV.append(float(np.abs(fwd.eq.arm_volumes(x) - fwd.eq.arm_volumes(xf)).max()))
                dP.append(float(np.linalg.norm(fwd.probe @ (x - xf).reshape(-1, 3), axis=1).max()))
                dF.append(abs(float(full[0][0] - lam[0])))
        cpu_full += check_cpu
        n_full += len(checked)
        rec = {**tr, "train_cpu_s": train_cpu, "train_wall_s": t1 - t, "grid_cpu_s": grid_cpu,
               "grid_wall_s": grid_wall, "check_cpu_s": check_cpu, "check_wall_s": time.perf_counter() - t2,
               "checks": len(checked), "check_max_dV_mm3": max(dV, default=np.nan) * 1e9,
               "check_max_points_mm": max(dP, default=np.nan) * 1e3, "check_max_fx_N": max(dF, default=np.nan),
               "unsolved": int(solved.size - solved.sum())}
        info["rounds"].append(rec)
        log.info(f"atlas (reduced) round {rnd + 1}: basis {tr['basis']}, {tr['elements']} ECSW elements, grid "
            f"{grid_cpu:.0f} CPU-s; {len(checked)} full checks: volumes within {rec['check_max_dV_mm3']:.3f} mm³, "
            f"points {rec['check_max_points_mm']:.4f} mm, f_x {rec['check_max_fx_N']:.4f} N")
        if not rec["check_max_dV_mm3"] > CHECK_DV_MM3 or rnd == MAX_ROUNDS - 1:
            break
        snaps += checked
    info.update({k: info["rounds"][-1][k] for k in ("basis", "elements", "checks", "check_max_dV_mm3",
                                                    "check_max_points_mm", "check_max_fx_N")})
    # the grid's outputs from the reduced states
    V = np.full((*shape, 4), np.nan)
    P = np.full((*shape, fwd.probe.shape[0], 3), np.nan)
    X = np.full((*shape, fwd.fem.n_dof), np.nan)
    for p in map(tuple, np.argwhere(solved)):
        x = rom.x(Q[p])
        V[p] = fwd.eq.arm_volumes(x)
        P[p] = fwd.probe @ x.reshape(-1, 3)
        X[p] = x - fwd.fem.x_rest
    return V, P, X, solved, F, QN, cpu_full + sum(r["train_cpu_s"] + r["grid_cpu_s"] for r in info["rounds"]), \
        n_full, info
