"""The atlas build: converged forward solves on the grid of an :class:`AtlasConfig`, in parallel
through :mod:`softphantom.parallel` (:func:`build_atlas`), fitted to tensor Chebyshev polynomials
(:class:`~softphantom.estimation.atlas.map.Atlas`). Where an atlas is looked up, and when it is
built and saved: :mod:`~softphantom.estimation.atlas.catalogue`.

On a force axis each task solves one (f_y, f_z) plane of the grid (:func:`_sweep`) walking
outwards from zero load, each point from a converged neighbour. On a displacement-controlled first
axis the graph is fine (:func:`_piece_tasks`): each face plane a spine along f_z from rest and a
branch along f_y from each spine point (:func:`_face_part`), then each line along q between its two
face points (:func:`_line_task`, one mixed-control solve a point, :func:`_solve_ux`). Points the
model cannot reach are recorded, filled by extrapolation (:func:`fill_weights`) and flagged outside
the envelope. The cost model (:func:`estimate_build`) predicts each task's CPU seconds, the build's
wall time on N workers and its critical path. What one task solves is in
:mod:`~softphantom.estimation.atlas.solves` (its names re-exported here).
"""

from __future__ import annotations

import logging
import math
import os
import platform
import shlex
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.estimation.atlas.basis import axis_t, to_chebyshev
from softphantom.estimation.atlas.config import (FALLBACK_MIN_LOAD_STEP, FIELD_MAX_MODES, FIELD_RTOL,  # noqa: F401
                                                NODE_TOL, VIA_TOL, AtlasConfig, default_atlas_config, x_patch)
from softphantom.estimation.atlas.identity import piece_keys, rest_record
from softphantom.estimation.atlas.map import Atlas, AtlasPatches, regroup
from softphantom.estimation.atlas.solves import (  # noqa: F401  (what one task solves; re-exported)
    GridPart, LinePredictor, _axis_derivative, _face_part, _inner, _line_knot, _line_task, _linearized_at, _lines,
    _plane_walk, _solve_ux, _sweep, face_segments)
from softphantom.estimation.atlas.tasks import (GraphRun, Task, TaskStore, bottom_levels, critical_path_s, partial_dir,
                                                run_graph, schedule_s)
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel

log = logging.getLogger(__name__)


def fill_weights(solved: np.ndarray, axes: list[np.ndarray]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """How to fill the grid points that did not converge, so the tensor fit is defined: a list of
    (flat index, source flat indices, weights), to apply in order. Each unsolved point takes, along
    every axis where its line has known points, the linear interpolation between the nearest known
    points on either side, or else the linear extrapolation from the two nearest on one side (one:
    its value), averaged over those axes; points with no known point on any line wait for a
    later pass, which also uses the points filled before it.

    >>> s = np.array([True, True, True, False, False])
    >>> [(t, src.tolist(), w.round(3).tolist()) for t, src, w in fill_weights(s, [np.arange(5.0)])]
    [(3, [2, 1], [2.0, -1.0]), (4, [2, 1], [3.0, -2.0])]
    """
    shape = solved.shape
    known = solved.copy()
    if not known.any():
        raise SolverError("atlas: no grid point converged")
    out = []
    while not known.all():
        batch = []
        for idx in map(tuple, np.argwhere(~known)):
            terms: list[tuple[list[int], list[float]]] = []
            for a, xs in enumerate(axes):
                line = list(idx)
                have = [m for m in range(shape[a]) if known[tuple(line[:a] + [m] + line[a + 1:])]]
                if not have:
                    continue
                x = xs[idx[a]]
                below = [m for m in have if m < idx[a]]
                above = [m for m in have if m > idx[a]]
                if below and above:
                    m1, m2 = below[-1], above[0]
                    w2 = (x - xs[m1]) / (xs[m2] - xs[m1])
                    src, w = [m1, m2], [1 - w2, w2]
                else:
                    side = below[::-1] if below else above  # nearest first
                    if len(side) == 1:
                        src, w = side[:1], [1.0]
                    else:
                        m1, m2 = side[:2]
                        w2 = (x - xs[m1]) / (xs[m2] - xs[m1])
                        src, w = [m1, m2], [1 - w2, w2]
                flat = [int(np.ravel_multi_index(tuple(line[:a] + [m] + line[a + 1:]), shape)) for m in src]
                terms.append((flat, w))
            if terms:
                src = np.concatenate([np.array(f) for f, _ in terms])
                w = np.concatenate([np.array(w) for _, w in terms]) / len(terms)
                batch.append((int(np.ravel_multi_index(idx, shape)), src, w))
        for t, _, _ in batch:
            known.flat[t] = True
        out.extend(batch)
    return out


def _fill(values: np.ndarray, weights) -> np.ndarray:
    """``values`` (n_grid, m) with the unsolved rows filled in place by :func:`fill_weights`."""
    for t, src, w in weights:
        values[t] = w @ values[src]
    return values


def provenance(model, fwd: ForwardModel) -> dict:
    """What an atlas records about its origin: enough to recompute its key from the model alone
    (the contact point and patch radius, the solver tolerance: :func:`softphantom.estimation.atlas.store.verify_atlas`)
    and to tell a user what it is (model name, nodes, element order, version, date)."""
    import datetime

    from softphantom import __version__

    c = fwd.config.contact
    argv = sys.argv if sys.argv and Path(sys.argv[0]).name in ("softphantom", "__main__.py") else None
    return {"softphantom": __version__, "model": getattr(getattr(model, "design", None), "name", ""),
            "command": shlex.join(["softphantom", *argv[1:]]) if argv else "",
            "machine": f"{platform.node()}: {platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
            "nodes": int(len(fwd.fem.x_rest) // 3), "element_order": int(fwd.fem.order),
            "contact": c if isinstance(c, str) else [float(v) for v in c],
            "contact_radius_m": float(fwd.config.contact_radius_m), "tol": float(fwd.config.tol),
            "built_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}


def _piece_tasks(model, cfg: EstimatorConfig, acfg: AtlasConfig, fwd: ForwardModel, tag: str, piece: int) -> list[Task]:
    """The tasks of one atlas (one piece along f_y): the (f_y, f_z) planes of a force axis
    (:func:`_sweep`, ``{tag}-plane-i-l``); on a displacement axis each face plane's segments
    (:func:`face_segments`: ``{tag}-spine-i-l``, then ``{tag}-branch-k-i-l`` from it), then each line
    along q (``{tag}-line-k-l-j``, :func:`_line_task`) depending on the two face segments that hold
    its end points. ``model``, ``cfg`` and ``fwd`` may be None for the graph's structure alone (the
    cost model, :func:`plan_tasks`)."""
    n1, n2, n3, n4 = acfg.shape
    hermite = acfg.hermite_axis
    kind = f"piece {piece}"
    planes = [(i, l) for l in range(1 if acfg.linear_pressure else n4) for i in range(n1)]
    if acfg.x_control == "force":
        return [Task(f"{tag}-plane-{i}-{l}", _sweep, lambda _r, i=i, l=l: (model, cfg, acfg, i, l),
                     points=n2 * n3, kind=f"{kind} plane", priority=1) for i, l in planes]
    # the fine graph (the critical path a few points long): each face plane's spine from rest, its
    # branches along f_y each seeded by a spine point, each line along q as soon as its two face
    # points are solved
    segs = face_segments(acfg)
    j0 = segs[0][1][0][0]
    faces = []
    for l in range(n4):
        for i in (0, n1 - 1):
            spine = f"{tag}-spine-{i}-{l}"
            faces.append(Task(spine, _face_part, lambda _r, i=i, l=l, pts=segs[0][1]: (model, cfg, acfg, i, l, pts),
                              points=len(segs[0][1]), kind=f"{kind} spine"))

            def branch_args(r, i=i, l=l, spine=spine, seg=None):
                name, pts = seg
                k = int(name.split("-")[1])
                sp = r[spine]
                row = sp.row(j0, k)
                return model, cfg, acfg, i, l, pts, ((j0, k), sp.X[row] if sp.solved[row] else None)

            for seg in segs[1:]:
                faces.append(Task(f"{tag}-{seg[0]}-{i}-{l}", _face_part,
                                  lambda r, f=branch_args, seg=seg: f(r, seg=seg), deps=(spine,),
                                  points=len(seg[1]), kind=f"{kind} branch"))

    def holder(i: int, l: int, j: int, k: int) -> str:
        return f"{tag}-spine-{i}-{l}" if j == j0 else f"{tag}-branch-{k}-{i}-{l}"

    def line_args(r, k, l, j):
        h = x_patch(fwd)
        ends, dends, start = [], [], None
        for i in (0, n1 - 1):
            part = r[holder(i, l, j, k)]
            row = part.row(j, k)
            ok = bool(part.solved[row])
            ends.append(float(part.X[row] @ h) if ok else math.nan)
            if i == 0:
                start = part.X[row]
            if hermite not in (None, 0):
                dends.append(float(part.derivs[2][row] @ h) if ok else math.nan)
        return model, cfg, acfg, k, l, j, tuple(ends), start, tuple(dends) if dends else None

    lines = [Task(f"{tag}-line-{k}-{l}-{j}", _line_task, lambda r, k=k, l=l, j=j: line_args(r, k, l, j),
                  deps=(holder(0, l, j, k), holder(n1 - 1, l, j, k)), points=n1 - 2, kind=f"{kind} line")
             for l in range(n4) for k in range(n3) for j in range(n2)]
    return faces + lines


def task_place(name: str, acfg: AtlasConfig) -> str:
    """Where on the grid a task of :func:`_piece_tasks` works, as a user reads it.

    >>> task_place("p0-plane-3-1", AtlasConfig()), task_place("p1-branch-2-0-1", AtlasConfig())
    ('piece 0, plane f_x index 3, pressure index 1', 'piece 1, face f_x index 0, f_z index 2, pressure index 1')
    >>> task_place("p0-line-2-1-4", AtlasConfig())
    'piece 0, line along q at f_y index 4, f_z index 2, pressure index 1'
    """
    tag, what, *n = name.split("-")
    piece = f"piece {tag[1:]}"
    if what == "plane":
        return f"{piece}, plane {'f_x' if acfg.x_control == 'force' else 'q'} index {n[0]}, pressure index {n[1]}"
    if what == "spine":
        return f"{piece}, face f_x index {n[0]} (its spine), pressure index {n[1]}"
    if what == "branch":
        return f"{piece}, face f_x index {n[1]}, f_z index {n[0]}, pressure index {n[2]}"
    return f"{piece}, line along q at f_y index {n[2]}, f_z index {n[0]}, pressure index {n[1]}"


def _assemble(model, fwd: ForwardModel, acfg: AtlasConfig, key: str, tag: str, run: GraphRun, t0: float) -> Atlas:
    """The atlas of one piece from its tasks' results (:func:`_piece_tasks`): the grid arrays, the
    unreachable points filled, the fit."""
    n1, n2, n3, n4 = acfg.shape
    ndof = fwd.fem.n_dof
    k = fwd.probe.shape[0]
    n_arms = len(fwd.eq.arm_names)
    V = np.empty((n1, n2, n3, n4, n_arms))
    P = np.empty((n1, n2, n3, n4, k, 3))
    X = np.empty((n1, n2, n3, n4, ndof), dtype=np.float64)
    solved = np.zeros((n1, n2, n3, n4), bool)
    FX = np.empty((n1, n2, n3, n4))
    QN = np.empty((n1, n2, n3, n4))  # the first coordinate of each point
    hermite = acfg.hermite_axis
    # derivatives along the Hermite axis (per unit load)
    dV, dP, dX, dFX = (np.empty_like(a) for a in (V, P, X, FX)) if hermite is not None else (None,) * 4
    ax = acfg.axes()
    cpu_s, n_fwd = 0.0, 0
    for name, value in run.values.items():
        if not name.startswith(f"{tag}-"):
            continue
        cpu_s += run.cpu_s[name]
        if isinstance(value, GridPart):
            sel = tuple(value.idx.T)
            n_fwd += value.n_solves
            V[sel], P[sel], X[sel], FX[sel], QN[sel], solved[sel] = (value.V, value.P, value.X, value.FX, value.Q,
                                                                   value.solved)
            if value.derivs is not None:
                dV[sel], dP[sel], dX[sel], dFX[sel] = value.derivs
            if not value.solved.all():
                log.info(f"atlas: {name.split('-', 1)[1]}: {int((~value.solved).sum())} of {len(value.solved)} points "
                         f"unreachable ({value.error or 'beyond a failed point'})")
            continue
        if "-lines-" in name:
            kz, lp, v, p, x, ok, err, _cpu, fx, q, n_tried, deriv = value
            n_fwd += n_tried
            V[1:-1, :, kz, lp], P[1:-1, :, kz, lp], X[1:-1, :, kz, lp] = v, p, x
            if deriv is not None:
                dV[1:-1, :, kz, lp], dP[1:-1, :, kz, lp], dX[1:-1, :, kz, lp], dFX[1:-1, :, kz, lp] = deriv
            FX[1:-1, :, kz, lp], QN[1:-1, :, kz, lp], solved[1:-1, :, kz, lp] = fx, q, ok
            if not ok.all():
                log.info(f"atlas: lines at f_z {ax[2][kz]:+.2f} N, urethra {ax[3][lp] * 1e-3:.1f} kPa: "
                         f"{ok.size - ok.sum()} of {ok.size} points unreachable ({err or 'beyond a failed point'})")
            continue
        i, l, v, p, x, ok, err, _cpu, deriv, fx, q, n_tried = value
        n_fwd += n_tried
        QN[i, :, :, l] = q
        if deriv is None or hermite is not None:
            V[i, :, :, l], P[i, :, :, l], X[i, :, :, l], FX[i, :, :, l] = v, p, x, fx
            solved[i, :, :, l] = ok
            if hermite is not None:
                dV[i, :, :, l], dP[i, :, :, l], dX[i, :, :, l], dFX[i, :, :, l] = deriv
        else:  # the tangent line in the pressure through the middle plane
            half = 0.5 * (ax[3][-1] - ax[3][0])
            for l, sgn in ((0, -half), (n4 - 1, half)):
                V[i, :, :, l], P[i, :, :, l], X[i, :, :, l] = (a + sgn * d for a, d in zip((v, p, x), deriv))
                FX[i, :, :, l], QN[i, :, :, l] = fx, q
                solved[i, :, :, l] = ok
        if not ok.all():
            p_u = 0.5 * (ax[3][0] + ax[3][-1]) if acfg.linear_pressure else ax[3][l]
            log.info(f"atlas: plane {'f_x' if acfg.x_control == 'force' else 'q'} {ax[0][i]:+.2f} N, urethra "
                     f"{p_u * 1e-3:.1f} kPa: {ok.size - ok.sum()} of {ok.size} points unreachable "
                     f"({err or 'beyond a failed point'})")
    if acfg.x_control == "displacement":
        extra = n_fwd - int(solved.sum())
        log.info(f"atlas: {n_fwd} converged forward solves for {int(solved.sum())} points" + (
            f" ({extra} more: force-controlled trials where a line point's mixed-control solve failed)" if extra else ""))
    return _fit(model, fwd, acfg, key, V, P, X, solved, FX, QN, (dV, dP, dX, dFX), cpu_s, t0, None)


def _fit(model, fwd, acfg, key, V, P, X, solved, FX, QN, derivs, cpu_s, t0, offline) -> Atlas:
    """The tensor Chebyshev fit of the solved grid (unreachable points filled first)."""
    ax = acfg.axes()
    ndof = fwd.fem.n_dof
    k = fwd.probe.shape[0]
    hermite = acfg.hermite_axis
    dV, dP, dX, dFX = derivs
    weights = fill_weights(solved, ax)
    grids = (V, P, X, FX) if hermite is None else (V, P, X, FX, dV, dP, dX, dFX)
    for a in grids:
        _fill(a.reshape(solved.size, -1), weights)
    shape = acfg.shape
    if hermite is not None:  # per unit of the axis's Chebyshev variable t: d/dt = d/dλ / (dt/dλ)
        if hermite == 0 and acfg.x_control == "displacement":  # per ū → per q: each line's ū spans the axis affinely
            h = x_patch(fwd)
            per_t = (X[-1] @ h - X[0] @ h) / (ax[0][-1] - ax[0][0]) / np.vectorize(axis_t)(
                QN, ax[0][0], ax[0][-1], acfg.stretch[0])[1]
        else:
            g = np.vectorize(axis_t)(ax[hermite], ax[hermite][0], ax[hermite][-1], acfg.stretch[hermite])[1]
            per_t = (1.0 / g).reshape([-1 if a == hermite else 1 for a in range(4)])
        dV, dP, dX, dFX = (d * per_t.reshape(per_t.shape + (1,) * (d.ndim - 4)) for d in (dV, dP, dX, dFX))
    D = X.reshape(-1, ndof)
    del X
    coef, dcoef, modes, field_rms = _pod(D, None if dX is None else dX.reshape(-1, ndof))
    r = modes.shape[1]
    # the first axis's Chebyshev variable at each point (a displacement axis's points are where
    # they landed: each line is fitted through its own, to_chebyshev)
    tq = np.vectorize(axis_t)(QN, ax[0][0], ax[0][-1], acfg.stretch[0])[0]

    def fit(values, d):
        return to_chebyshev(values, shape, tq, None if d is None else (hermite, d))

    cV = fit(V.reshape(*shape, V.shape[-1]), None if dV is None else dV.reshape(*shape, V.shape[-1]))
    cP = fit(P.reshape(*shape, k * 3), None if dP is None else dP.reshape(*shape, k * 3))
    cP = cP.reshape(*acfg.coef_shape, k, 3)
    cF = fit(coef.reshape(*shape, r), None if dcoef is None else dcoef.reshape(*shape, r))
    # f_x as an output: on a displacement axis the polynomial of the solved f_x; on a force axis
    # f_x is the axis variable itself (its polynomial is not needed, and not exact on a stretch)
    cFx = (fit(FX[..., None], None if dFX is None else dFX[..., None]) if acfg.x_control == "displacement"
           else np.zeros((*acfg.coef_shape, 0)))
    return Atlas(key=key, config=acfg, cV=cV, cP=cP, cF=cF, cFx=cFx, q_nodes=QN, modes=modes, x_rest=fwd.fem.x_rest.copy(),
                 build_s=time.perf_counter() - t0, solves=int(solved.sum()) * acfg.n_solves // solved.size,
                 field_rms_m=field_rms, solved=solved, build_cpu_s=cpu_s,
                 provenance={**provenance(model, fwd), **({"offline": offline} if offline else {})})


# The cost model: CPU-s a grid point of each kind, per element order at the model size given (the
# BIP: linear 6 mm, 6 352 nodes; quadratic 9 mm with 2 mm arms, 28 329 nodes, Hermite f_z), with
# the pardiso extra. Quadratic: a face plane's first point from rest 27
# (benchmarks/bench_atlas_point_cost.py); a face point 7.2 CPU-s and a line point 3.65 below the
# fold, 12.6 and 32 above it (f_y above FOLD_F_Y_N: the arm pair snaps through) — the shipped
# build's provenance averaged 9.9 and 18 over the upper piece, half of whose f_y points are above.
# The fold's points cost 1.5x with SuperLU for their indefinite tangents (NO_PARDISO_FACTOR).
# Another model scales with its nodes squared (a 3-D sparse factorization's work): the 12 mm
# quadratic model's default atlas took 4 933 CPU-s at 13 699 nodes, the 9 mm one's 23 435 at 28 329.
POINT_COST_S = {1: ({"rest": 2.7, "face": 0.45, "line": 0.45}, {"face": 0.45, "line": 0.45}, 6352),
                2: ({"rest": 27.0, "face": 7.2, "line": 3.65}, {"face": 12.6, "line": 32.0}, 28329)}
NODES_EXPONENT = 2.0
# the line points' costs are for the default's 9 inner q points a line; with fewer each step is
# longer and costs more: the 12 mm quadratic model's draft (3 inner points) cost 6x the model's
# prediction by points alone in its lines, (9 / 3) ** 1.5 = 5.2
LINE_REF_POINTS = 9
LINE_STEP_EXPONENT = 1.5
FOLD_F_Y_N = 4.29  # the quadratic default's snap-through starts here along f_y: the fold's rates above it
NO_PARDISO_FACTOR = {1: 1.0, 2: 1.5}
# an estimator (estimate, live) builds a missing atlas itself only below this wall time; above it
# says how to build it (``softphantom atlas build``, resumable) and how to go on meanwhile
MAX_BUILD_ON_THE_FLY_S = 600.0


class AtlasMissing(UserError):
    """A model without its atlas, whose build takes longer than a command should wait for."""


class DraftRefused(UserError):
    """A draft atlas where the full one is required (``--require-full``)."""


def draft_points(order: int) -> int:
    """Grid points of the draft atlas of a model of element ``order``."""
    from softphantom.estimation.atlas.config import draft_atlas_config

    return draft_atlas_config(order).n_solves


def point_costs(order: int, nodes: int, pardiso: bool | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """CPU-s a grid point of each kind (``rest``: a face plane's first, from rest; ``face``; ``line``)
    for a model of element ``order`` with ``nodes`` nodes, below and above the fold
    (:data:`FOLD_F_Y_N`): :data:`POINT_COST_S` scaled by the nodes (:data:`NODES_EXPONENT`), the
    fold's times :data:`NO_PARDISO_FACTOR` without the ``pardiso`` extra (None: whether it is installed).

    >>> point_costs(2, 28329, pardiso=True)[0], point_costs(2, 28329, pardiso=False)[1]["line"]
    ({'rest': 27.0, 'face': 7.2, 'line': 3.65}, 48.0)
    """
    from softphantom.fem import have_pardiso

    o = 2 if int(order) == 2 else 1
    base, fold, ref_nodes = POINT_COST_S[o]
    f = 1.0 if (have_pardiso() if pardiso is None else pardiso) else NO_PARDISO_FACTOR[o]
    s = (nodes / ref_nodes) ** NODES_EXPONENT
    return {k: v * s for k, v in base.items()}, {**{k: v * s for k, v in base.items()},
                                                   **{k: v * f * s for k, v in fold.items()}}


def _task_cost(task: Task, acfg: AtlasConfig, costs) -> float:
    """Predicted CPU-s of a task of :func:`_piece_tasks` for the piece ``acfg``: its points' costs
    (:func:`point_costs`, the fold's above :data:`FOLD_F_Y_N` on the quadratic model)."""
    _, what, *n = task.name.split("-")
    f_y = acfg.axes()[1]
    if what in ("line", "lines"):
        ys = [f_y[int(n[2])]] if what == "line" else list(f_y)
        # a longer step along q costs more a point: LINE_STEP_EXPONENT, fitted on the draft grid's lines
        step = (LINE_REF_POINTS / max(acfg.shape[0] - 2, 1)) ** LINE_STEP_EXPONENT
        return task.points / len(ys) * step * sum(costs[y > FOLD_F_Y_N]["line"] for y in ys)
    j0 = face_segments(acfg)[0][1][0][0]
    ys = {"spine": [f_y[j0]], "branch": [y for j, y in enumerate(f_y) if j != j0]}.get(what, list(f_y))
    per = sum(costs[y > FOLD_F_Y_N]["face"] for y in ys) / len(ys)
    rest = costs[False]["rest"] if what in ("plane", "spine") else 0.0
    return rest + (task.points - (1 if rest else 0)) * per


def plan_tasks(order: int, nodes: int, acfg: AtlasConfig, pardiso: bool | None = None, tasks=None) -> list[Task]:
    """The build's tasks (``tasks``, or the structure of :func:`_piece_tasks` for every piece of
    ``acfg`` without their functions) with their predicted CPU-s (``Task.cost``) and, as their Dask
    priorities, their bottom levels (:func:`~softphantom.estimation.atlas.tasks.bottom_levels`):
    the long chains first."""
    subs = acfg.pieces()
    if tasks is None:
        tasks = [t for p, sub in enumerate(subs) for t in _piece_tasks(None, None, sub, None, f"p{p}", p)]
    lo, fold = point_costs(order, nodes, pardiso)
    costs = {False: lo, True: fold}
    tasks = [replace(t, cost=_task_cost(t, subs[int(t.name.split("-")[0][1:])], costs)) for t in tasks]
    level = bottom_levels(tasks, {t.name: t.cost for t in tasks})
    top = int(round(max(level.values(), default=0.0) * 10)) + 1
    # a probe: each kind's first task runs as soon as it can, so the ETA measures every kind early
    # (the longest chains first would leave the lines, the cheap end of each chain, to the last half)
    first: dict[str, str] = {}
    for t in tasks:
        if t.kind not in first and all(d.split("-")[1] in ("spine",) for d in t.deps):
            first[t.kind] = t.name
    probes = set(first.values())
    return [replace(t, priority=top if t.name in probes else int(round(level[t.name] * 10))) for t in tasks]


@dataclass(frozen=True)
class BuildEstimate:
    """A build's predicted cost (:func:`estimate_build`): ``cpu_s``, ``wall_s`` on ``workers`` idle
    cores, ``critical_path_s`` (its wall time on a cluster of a worker per task), ``tasks``."""

    cpu_s: float
    wall_s: float
    critical_path_s: float
    workers: int
    tasks: int


def estimate_build(order: int, nodes: int, acfg: AtlasConfig, workers: int | None = None,
                   pardiso: bool | None = None) -> BuildEstimate:
    """The cost model of building ``acfg`` for a model of element ``order`` with ``nodes`` nodes,
    before any task ran: each task's predicted CPU-s (:func:`plan_tasks`), scheduled on ``workers``
    idle cores as the build schedules them (:func:`~softphantom.estimation.atlas.tasks.schedule_s`);
    the build's own ETA takes over once tasks end (:class:`~softphantom.estimation.atlas.tasks.Eta`).

    >>> from softphantom.estimation.atlas.config import default_atlas_config
    >>> e = estimate_build(2, 28329, default_atlas_config(2), workers=2, pardiso=True)
    >>> round(e.cpu_s), round(e.wall_s), round(e.critical_path_s), e.tasks
    (20710, 10371, 396, 252)
    """
    w = max(1, int(workers or os.cpu_count() or 1))
    tasks = plan_tasks(order, nodes, acfg, pardiso)
    cost = {t.name: t.cost for t in tasks}
    return BuildEstimate(sum(cost.values()), schedule_s(tasks, cost, w),
                         max(bottom_levels(tasks, cost).values(), default=0.0), w, len(tasks))


def estimated_build(order: int, nodes: int, acfg: AtlasConfig, workers: int | None = None,
                    pardiso: bool | None = None) -> tuple[float, float]:
    """(CPU-s, wall-s on ``workers`` idle cores) of :func:`estimate_build`."""
    e = estimate_build(order, nodes, acfg, workers, pardiso)
    return e.cpu_s, e.wall_s


def duration_text(seconds: float) -> str:
    """A build's duration as a user reads it: minutes, or hours from 1.5 h.

    >>> duration_text(290), duration_text(9000)
    ('5 min', '2.5 h')
    """
    return f"{seconds / 3600:.1f} h" if seconds >= 5400 else f"{max(1, round(seconds / 60))} min"


def build_settings(config: EstimatorConfig, acfg: AtlasConfig, n_nodes: int) -> dict:
    """What identifies a build command: the atlas settings (all pieces) and the estimator settings
    its key depends on; an interrupted build resumes only under the same
    (:func:`~softphantom.estimation.atlas.tasks.check_partials`)."""
    c = config.contact
    return {"atlas": acfg.as_dict(), "contact": c if isinstance(c, str) else [float(v) for v in c],
            "contact_radius_m": float(config.contact_radius_m), "tol": float(config.tol), "nodes": int(n_nodes)}


def check_atlas_cavities(model) -> str:
    """The atlas tabulates λ = (f, p_1) with p_1 the gauge pressure of the model's first actuated
    internal cavity (the BIP's urethra, a kidney's collecting system; a measured cavity is a volume
    row, not a load), and a stack of such atlases over the further ones' pressures
    (``AtlasConfig.further_min_kPa``): returns the first cavity's name; a model without an actuated
    internal cavity is refused in one line (the refresh estimator takes it)."""
    names = model.layout.actuated
    if not names:
        raise UserError("cavities: the atlas tabulates at least one internal pressure; this design has 0: "
                        "use --estimator refresh")
    return names[0]


def build_atlas(model, config: EstimatorConfig | None = None, atlas: AtlasConfig | None = None, *,
                keys: tuple[str, ...] | None = None, scheduler: str | None = None, n_workers: int | None = None,
                fwd: ForwardModel | None = None, processes: bool = True, cache_dir=None,
                pieces: tuple[int, ...] | None = None) -> Atlas | AtlasPatches:
    """Build the atlas of ``model`` (forward solves in parallel, a Dask local cluster by default or
    the one at ``scheduler``; ``processes=False``: worker threads, for small models and tests).
    ``atlas`` None: :func:`default_atlas_config` of the model's element order. With ``f_y_splits_N``
    the pieces' tasks run as one graph (:mod:`~softphantom.estimation.atlas.tasks`); ``pieces``: the
    indices of the pieces to build (default all; the result then holds only those, in order).

    ``keys``: each piece's key (:func:`~softphantom.estimation.atlas.catalogue.piece_keys`, computed
    when not given). With ``cache_dir`` (a model directory) each finished task is kept in
    ``MODEL/atlas/partial/<key>/``, so an interrupted build started again goes on where it stopped;
    the kept tasks are deleted once the atlas is saved
    (:func:`~softphantom.estimation.atlas.catalogue.find_or_build`).

    A corner of the envelope box may be physically unreachable for the model (e.g. a large push
    with sideways force inverts an element under a point contact). Such grid points are recorded,
    not fatal: each plane walks outwards from zero load and does not try points beyond one that
    failed (:func:`_sweep`); the unsolved points are filled by linear extrapolation from their
    converged neighbours along the grid lines (:func:`fill_weights`) so the tensor fit is defined,
    and every grid cell with an unsolved corner is outside the envelope (``Atlas.solved_at``; the
    estimator's ``in_envelope`` is False there). Logs one line per plane with failures and a
    summary, and the tasks' progress as done/total records with the time left
    (:func:`softphantom.progress.report`). Raises :class:`~softphantom.errors.SolverError` only if
    no point converged."""
    check_atlas_cavities(model)
    from softphantom.parallel import dask_client

    cfg = config or EstimatorConfig()
    fwd = fwd or ForwardModel(model, cfg)
    acfg = (atlas or default_atlas_config(fwd.fem.order)).for_cavities(len(model.layout.actuated))
    subs = acfg.pieces()
    which = tuple(range(len(subs))) if pieces is None else tuple(pieces)
    t0 = time.perf_counter()
    if keys is None:
        keys = piece_keys(model, cfg, acfg)
    keys = {p: keys[p] for p in which}
    if acfg.offline == "rom":  # the grid by a reduced model (softphantom.estimation.offline), piece by piece
        from softphantom.estimation.offline import rom_grid

        built = []
        for p in which:
            with dask_client(scheduler, n_workers, processes=processes) as client:
                V, P, X, solved, FX, QN, cpu_s, _n, offline = rom_grid(model, cfg, subs[p], fwd, client)
            built.append(_fit(model, fwd, subs[p], keys[p], V, P, X, solved, FX, QN, (None,) * 4, cpu_s, t0, offline))
    else:
        tasks = plan_tasks(fwd.fem.order, fwd.fem.n_dof // 3, acfg,
                           tasks=[t for p in which for t in _piece_tasks(model, cfg, subs[p], fwd, f"p{p}", p)])
        settings = build_settings(cfg, acfg, fwd.fem.n_dof // 3)
        stores = {p: TaskStore(partial_dir(cache_dir, keys[p]), {"build": settings, "key": keys[p]})
                  for p in which} if cache_dir is not None else {}

        def store_of(name: str):
            return stores.get(int(name.split("-")[0][1:]))

        def failed(task: Task, msg: str) -> Exception:  # not a solver failure (those are recorded): a bug, a lost worker
            return SolverError(f"atlas: {task_place(task.name, acfg)} failed: {msg}")

        n_points = sum(t.points for t in tasks)
        label = f"atlas: {len(tasks)} tasks, {n_points} grid points"
        with dask_client(scheduler, n_workers, processes=processes) as client:
            n_cores = sum(client.nthreads().values())
            run = run_graph(client, tasks, store_of, label, failed)
        built = [_assemble(model, fwd, subs[p], keys[p], f"p{p}", run, t0) for p in which]
        wall = time.perf_counter() - t0
        crit = critical_path_s(tasks, run.wall_s)
        cpu = sum(run.cpu_s.values())
        log.info(f"atlas: {len(tasks)} tasks, {cpu:.0f} CPU-s ({len(run.kept)} kept from an interrupted build), "
                 f"{wall:.0f} s wall on {n_cores} workers: parallel efficiency "
                 f"{cpu / max(wall * n_cores, 1e-9):.0%}; critical path {crit:.0f} s (the wall time on a cluster "
                 f"of {len(tasks)} workers)")
        for a in built:
            a.provenance["build"] = {"workers": n_cores, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
                                     "critical_path_s": round(crit, 1), "tasks": len(tasks),
                                     "kept_tasks": len(run.kept),
                                     # each task's CPU-s and wall-s: the graph's behaviour on other clusters
                                     "task_s": {n: [round(run.cpu_s[n], 2), round(run.wall_s[n], 2)]
                                                for n in sorted(run.wall_s)}}
    for a in built:  # what verify_atlas recomputes from the model to catch a stale atlas
        a.provenance["rest"] = rest_record(a, model, fwd)
    if len(subs) == 1:
        return built[0]
    if pieces is None:
        return regroup(acfg, dict(enumerate(built)))
    return built  # type: ignore[return-value] - the pieces asked for, for find_or_build


def _pod(D: np.ndarray, dD: np.ndarray | None = None):
    """POD of the displacement snapshots ``D`` (n_grid, 3N) through their Gram matrix (n_grid² is
    small): (the snapshots' mode coefficients (n_grid, r), the derivatives' (or None), the modes
    (3N, r) with orthonormal columns, the RMS truncation error of ``D``). With derivative snapshots
    ``dD`` (a Hermite axis, per unit of its t: metres like ``D``) the basis is of both, and keeps
    modes until each set's dropped energy is below ``FIELD_RTOL`` of its own (the derivatives
    carry the field between the fewer points: a basis of the values alone misses it there)."""
    S = D if dD is None else np.vstack([D, dD])
    w, Q = np.linalg.eigh(S @ S.T)
    w, Q = w[::-1].clip(min=0.0), Q[:, ::-1]
    total = float(w.sum())
    tail = total - np.cumsum(w)
    if dD is None:
        r = int(min(FIELD_MAX_MODES, max(1, np.searchsorted(-tail, -FIELD_RTOL * total) + 1)))
        modes = S.T @ (Q[:, :r] / np.sqrt(np.maximum(w[:r], 1e-300)))  # (3N, r), orthonormal columns
        coef = D @ modes  # (n_grid, r)
        return coef, None, modes, float(np.sqrt(max(tail[r - 1], 0.0) / D.size))
    keep = w > 1e-14 * w[0]
    modes = S.T @ (Q[:, keep] / np.sqrt(w[keep]))
    # a mode's coefficients over S are Q's column times its singular value: each set's share
    c2 = (Q[:, keep] ** 2) * w[keep]
    n = len(D)
    r = 1
    for part in (slice(0, n), slice(n, None)):
        e = c2[part].sum(axis=0)
        left = float(e.sum()) - np.cumsum(e)
        r = max(r, int(np.searchsorted(-left, -FIELD_RTOL * float(e.sum())) + 1))
    r = min(r, FIELD_MAX_MODES, modes.shape[1])
    modes = modes[:, :r]
    coef = D @ modes
    rest = float(np.einsum("ij,ij->", D, D)) - float(np.einsum("ij,ij->", coef, coef))
    return coef, dD @ modes, modes, float(np.sqrt(max(rest, 0.0) / D.size))
