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
wall time on N workers and its critical path.
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
from softphantom.estimation.atlas.tasks import (GraphRun, Task, TaskStore, bottom_levels, critical_path_s, partial_dir,
                                                run_graph, schedule_s)
from softphantom.estimation.config import EstimatorConfig
from softphantom.estimation.forward import ForwardModel
from softphantom.estimation.linearization import PatchControl

UX_MAX_ITER = 30
BORDERED_HALVINGS = 2  # a mixed-control step that fails is split in two, and each half again
BORDERED_TOL = 1e-3  # a mixed-control solve hits the patch displacement this close (of NODE_TOL's): on the node

log = logging.getLogger(__name__)


class _HeldSolver:
    """An :class:`~softphantom.estimation.linearization.EquilibriumSolver` whose callers pass the
    first four loads (f, p_1): the further pressures are appended (``held`` (M − 1,) Pa)."""

    def __init__(self, eq, held: np.ndarray) -> None:
        self._eq = eq
        self._held = held

    def __getattr__(self, name):
        return getattr(self._eq, name)

    def _full(self, lam) -> np.ndarray:
        lam = np.asarray(lam, float)
        return lam if len(lam) == self._eq.n_loads else np.concatenate([lam[:4], self._held])

    def factorize(self, x, p) -> None:
        p = np.atleast_1d(np.asarray(p, float))
        self._eq.factorize(x, p if len(p) == self._eq.n_loads - 3 else np.concatenate([p[:1], self._held]))

    def residual(self, x, lam):
        return self._eq.residual(x, self._full(lam))

    def linearize(self, x, lam, *args, **kw):
        return self._eq.linearize(x, self._full(lam), *args, **kw)

    def solve(self, start, lam, *args, **kw):
        return self._eq.solve(start, self._full(lam), *args, **kw)


class HeldLoads:
    """A :class:`ForwardModel` with the pressures of the further cavities p_2 … p_M held at a
    stack level's (``held_Pa``): its :meth:`solve` and ``eq`` take λ = (f, p_1) as a one-pressure
    model's do and solve the full λ; the linearizations it returns are the full model's (λ (3 + M,),
    ``W`` (rows, 3 + M)), whose first four load columns the build reads. So a level is built by the
    same code as any atlas."""

    def __init__(self, fwd: ForwardModel, held_Pa) -> None:
        held = np.asarray(held_Pa, float)
        if len(held) != fwd.eq.n_loads - 4:
            raise UserError(f"atlas held_kPa: {len(held)} pressures held, the model has "
                            f"{fwd.eq.n_loads - 4} actuated cavities after the first")
        self._fwd = fwd
        self.held_Pa = held
        self.eq = _HeldSolver(fwd.eq, held)

    def __getattr__(self, name):
        return getattr(self._fwd, name)

    def solve(self, lam, start=None, **kw):
        return self._fwd.solve(self.eq._full(lam), start, **kw)


_FEM: dict[int, tuple] = {}  # a worker's FEM model of the phantom its tasks share (id(model) -> (model, fem))


def _task_forward(model, config: EstimatorConfig, acfg: AtlasConfig):
    """The forward model a build task solves with: a new solver (no factor, no state from another
    task, so a task's result does not depend on which ran before it on the worker) on the worker's
    FEM model of ``model``, assembled once per worker (1.4 CPU-s on the quadratic default model,
    as much as a grid point; a build has hundreds of tasks)."""
    from softphantom.fem import fem_from_phantom

    got = _FEM.get(id(model))
    if got is None or got[0] is not model:
        _FEM.clear()
        got = _FEM[id(model)] = (model, fem_from_phantom(model))
    # only the equilibria are kept: the sensitivities come from the kept factor (no GMRES), which
    # is the tangent at the start point's equilibrium; failures are expected at the envelope's
    # corners: the Newton fallback gives up at 1/32 of the load (not 1/1024: a failing solve cost
    # ~10 converging ones)
    return held_loads(ForwardModel(model, config, fem=got[1], exact_sensitivities=False,
                                   fallback_min_load_step=FALLBACK_MIN_LOAD_STEP), acfg)


def held_loads(fwd: ForwardModel, acfg: AtlasConfig):
    """``fwd`` as the build of the atlas ``acfg`` solves it: itself, or for a stack's level
    (``acfg.held_kPa``) the :class:`HeldLoads` view holding the further pressures."""
    return HeldLoads(fwd, np.asarray(acfg.held_kPa, float) * 1e3) if acfg.held_kPa else fwd


def _inner(p: tuple[int, int], centre: tuple[int, int]) -> list[tuple[int, int]]:
    """The neighbours of grid point ``p`` one step nearer ``centre`` along each axis."""
    j, k = p
    j0, k0 = centre
    out = []
    if j != j0:
        out.append((j - (1 if j > j0 else -1), k))
    if k != k0:
        out.append((j, k - (1 if k > k0 else -1)))
    return out


def _children(p: tuple[int, int], centre: tuple[int, int], ny: int, nz: int) -> list[tuple[int, int]]:
    """The points solved from ``p`` in a plane's walk: a spine along f_z through the centre, a
    branch along f_y from each spine point (a sideways step is the hard one for the solver: the
    fewest of them). A spine point's branches come before the next spine point, so every point's
    inner neighbours (:func:`_inner`) are solved before it."""
    j, k = p
    j0, k0 = centre
    if j != j0:
        out = [(j + (1 if j > j0 else -1), k)]
    else:
        out = [(j0 + 1, k), (j0 - 1, k)]
        out += [(j0, k0 + 1), (j0, k0 - 1)] if k == k0 else [(j0, k + (1 if k > k0 else -1))]
    return [(a, b) for a, b in out if 0 <= a < ny and 0 <= b < nz]


def _plane_walk(ny: int, nz: int, j0: int, k0: int) -> list[tuple[tuple[int, int], tuple[int, int] | None, int]]:
    """The (f_y, f_z) grid points of a plane from the one nearest zero load outwards, depth first
    along :func:`_children`: (point, the point it is solved from (None: from rest), number of points
    solved from it). Depth first, a point's start is the point solved just before it except after a
    branch's end, so the walk keeps the factors of only a few points (:func:`_sweep`).

    >>> [p for p, _, _ in _plane_walk(3, 3, 1, 1)]
    [(1, 1), (2, 1), (0, 1), (1, 2), (2, 2), (0, 2), (1, 0), (2, 0), (0, 0)]
    """
    centre = (j0, k0)
    out = []
    stack: list[tuple[tuple[int, int], tuple[int, int] | None]] = [(centre, None)]
    while stack:
        p, parent = stack.pop()
        kids = _children(p, centre, ny, nz)
        out.append((p, parent, len(kids)))
        stack.extend((c, p) for c in reversed(kids))
    return out


def _sub_walk(walk, keep: set) -> list:
    """The entries of a plane walk (:func:`_plane_walk`) at the points in ``keep``, in its order,
    each point's parent outside ``keep`` replaced by None and its children counted within ``keep``.

    >>> [(p, q, n) for p, q, n in _sub_walk(_plane_walk(3, 3, 1, 1), {(1, 2), (2, 2), (0, 2)})]
    [((1, 2), None, 2), ((2, 2), (1, 2), 0), ((0, 2), (1, 2), 0)]
    """
    out = [(p, q if q in keep else None) for p, q, _ in walk if p in keep]
    kids: dict = {}
    for _, q in out:
        kids[q] = kids.get(q, 0) + 1
    return [(p, q, kids.get(p, 0)) for p, q in out]


class LinePredictor:
    """A displacement axis's line ū ↦ (f_x N, x (3N,) m) near its last solved points, from their
    exact derivatives along ū (:func:`_line_knot`): the cubic Hermite through the last two, or the
    tangent line of the only one, evaluated beyond them. Its error falls with the fourth power of
    the step where the secant's falls with the second, so a line's next point (a tenth of the
    axis away) starts its chord iterations a few per cent of the load off instead of at about
    the load itself.

    >>> import numpy as np
    >>> p = LinePredictor()
    >>> for u in (0.0, 0.5):  # a cubic path: predicted exactly
    ...     p.add(u, np.array([u ** 3, u]), u ** 3, np.array([3 * u ** 2, 1.0]), 3 * u ** 2)
    >>> fx, x = p(1.0)
    >>> round(fx, 12), x.round(12).tolist()
    (1.0, [1.0, 1.0])
    """

    def __init__(self) -> None:
        self.knots: list[tuple[float, np.ndarray, float, np.ndarray, float]] = []

    def add(self, u: float, x: np.ndarray, fx: float, dx: np.ndarray, dfx: float) -> None:
        """A solved point at patch displacement ``u`` (m): state ``x``, force ``fx`` and their
        derivatives per metre of ū; the oldest of three is dropped."""
        self.knots = [*self.knots[-1:], (float(u), x, float(fx), dx, float(dfx))]

    def reset(self) -> None:
        self.knots = []

    def __call__(self, u: float) -> tuple[float, np.ndarray]:
        ub, xb, fb, dxb, dfb = self.knots[-1]
        if len(self.knots) == 1:
            return fb + dfb * (u - ub), xb + dxb * (u - ub)
        ua, xa, fa, dxa, dfa = self.knots[0]
        H = ub - ua
        t = (u - ua) / H
        h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, 3 * t**2 - 2 * t**3, t**3 - t**2
        return (h00 * fa + h10 * H * dfa + h01 * fb + h11 * H * dfb,
                h00 * xa + h10 * H * dxa + h01 * xb + h11 * H * dxb)


def _solve_ux(fwd: ForwardModel, h: np.ndarray, lam: np.ndarray, target: float, start, bracket,
              tol_m: float, bordered: bool = True, prev=None, fx_range=None, predictor=None) -> tuple:
    """The equilibrium at (f_y, f_z, p_u) = ``lam[1:]`` whose patch displacement ū_x = hᵀ(x − x_rest)
    is ``target`` (m) within ``tol_m``, and the number of solves it took: f_x by Newton on
    ū_x(f_x), the slope the secant of the last two trials (the first: the solve's own ∂ū_x/∂f_x,
    from a factor that may be stale where the state steps), kept inside ``bracket`` (f_x, N, at
    whose ends ū_x lies below and above the target: a stable path's ū_x increases with f_x) and
    bisecting it where Newton leaves it; ``lam[0]`` the first guess. Each trial is a converged
    force-controlled solve (:meth:`ForwardModel.solve`) from the previous one.

    First, though, one mixed-control solve (:class:`PatchControl`: f_x an unknown of bordered chord
    iterations, to ``BORDERED_TOL`` of ``tol_m``) from ``start`` (with ``prev``, the point before it
    on the line: a secant predictor; with a ``predictor``, :class:`LinePredictor`, its prediction
    instead), its f_x anywhere in ``fx_range`` (default ``bracket``): where
    the state snaps through in f_x (the quadratic model's arm pair above ≈ 4.3 N of f_y) the path at
    fixed ū_x goes through a fold, f_x falling on its unstable branch, which no force-controlled
    solve reaches. The trials above only where it fails, or without ``bordered`` (the
    force-controlled-only build, the benchmarks' peer)."""
    lo, hi = (float(b) for b in bracket)
    x_rest = fwd.fem.x_rest
    if bordered:
        rng = tuple(float(b) for b in (bracket if fx_range is None else fx_range))
        lin = _bordered(fwd, h, lam, float(target), start, prev, rng, BORDERED_TOL * tol_m, BORDERED_HALVINGS,
                        predictor)
        if lin is not None:
            return lin, 1
    f = float(lam[0])
    lin = start
    trial = np.array(lam, float)
    prev = None
    for n in range(1, UX_MAX_ITER + 1):
        if not lo < f < hi:
            f = 0.5 * (lo + hi)
        trial[0] = f
        lin = fwd.solve(trial, lin, via_tol=VIA_TOL)
        g = float(h @ (lin.x - x_rest)) - target
        if abs(g) <= tol_m:
            return lin, n
        if g < 0:
            lo = f
        else:
            hi = f
        d = (g - prev[1]) / (f - prev[0]) if prev is not None and f != prev[0] else float(h @ lin.U[:, 0])
        prev = (f, g)
        f = f - g / d if d > 0 else math.nan
    raise SolverError(f"atlas: no f_x in [{lo:+.4f}, {hi:+.4f}] N gives the patch displacement "
                      f"{target * 1e3:+.4f} mm at f_y {lam[1]:+.2f} N, f_z {lam[2]:+.2f} N")


def _bordered(fwd: ForwardModel, h: np.ndarray, lam: np.ndarray, target: float, start, prev, bracket, tol_m: float,
              halvings: int, predictor=None):
    """The mixed-control equilibrium at patch displacement ``target`` (m) from ``start`` (``prev``
    the point before it on the line, or None; ``predictor`` a :class:`LinePredictor`, or None: the
    secant), f_x kept inside ``bracket``; where it does not converge, the step in displacement is
    halved (up to ``halvings`` times, each half from the last converged state, the second on the
    secant through it). None where that fails too."""
    ctl = PatchControl(h, fwd.fem.x_rest, target, tol_m, prev, tuple(bracket), predictor)
    try:
        return fwd.eq.solve(start, lam, control=ctl)
    except SolverError:
        if halvings <= 0:
            return None
    mid = 0.5 * (target + float(h @ (start.x - fwd.fem.x_rest)))
    half = _bordered(fwd, h, lam, mid, start, prev, bracket, tol_m, halvings - 1, predictor)
    if half is None:
        return None
    return _bordered(fwd, h, lam, target, half, start, bracket, tol_m, halvings - 1)


def _axis_derivative(fwd: ForwardModel, lin, a: int, h: np.ndarray | None, du_q: float | None = None, col0=None):
    """The exact derivatives of a grid point's outputs along the Hermite axis ``a``
    (:meth:`~softphantom.estimation.linearization.EquilibriumSolver.exact_column`): (dV (n_arms,), dP
    (k, 3), dX (3N,), df_x) per unit load, at fixed f_x (``h`` None: a force axis, or a displacement
    axis's faces). On a displacement axis (``h`` the patch's x load vector, u_a = K⁻¹b_a):
    along ū = hᵀ(x − x_rest) itself (``a`` 0) per metre at fixed (f_y, f_z, p_u): u_0 / hᵀu_0 and
    df_x/dū = 1/hᵀu_0; along another load at fixed q (``du_q`` = dū/dλ_a there, the faces' ū
    derivatives mixed as q mixes their ū): u_a + c·u_0 with f_x's c = (du_q − hᵀu_a)/hᵀu_0 — the
    mixed-control derivative at fixed ū plus the move of ū itself. ``col0``: the f_x column
    (``exact_column(lin, 0)``) where the caller has it already."""
    dV, dP, dX = col0 if a == 0 and col0 is not None else fwd.eq.exact_column(lin, a)
    if h is None:
        return dV, dP, dX, 0.0
    if a == 0:
        s = float(h @ dX)
        return dV / s, dP / s, dX / s, 1.0 / s
    dV0, dP0, dX0 = col0 if col0 is not None else fwd.eq.exact_column(lin, 0)
    c = (du_q - float(h @ dX)) / float(h @ dX0)
    return dV + c * dV0, dP + c * dP0, dX + c * dX0, c


def _linearized_at(fwd: ForwardModel, x: np.ndarray, lam: np.ndarray):
    """The :class:`~softphantom.estimation.linearization.Linearization` at a state ``x`` (3N,) m
    already in equilibrium under ``lam`` (another task solved it), with the tangent there factored."""
    fwd.eq.factorize(x, float(lam[3]))
    r, ref = fwd.eq.residual(x, lam)
    return fwd.eq.linearize(x, lam, float(np.linalg.norm(r)) / max(ref, 1e-300), 0, True)


def _line_knot(fwd: ForwardModel, h: np.ndarray, lin, path: LinePredictor):
    """Add ``lin`` (a solved point of a line) to ``path`` with its exact derivatives along ū, and
    return its f_x column (``exact_column(lin, 0)``: dV, dP, dX per N) for a Hermite q axis; where
    the tangent there cannot be solved, or ū does not move with f_x, the path starts again."""
    try:
        col = fwd.eq.exact_column(lin, 0)
    except SolverError:
        path.reset()
        return None
    s = float(h @ col[2])  # dū/df_x (m/N)
    if s == 0.0 or not np.isfinite(s):
        path.reset()
        return col
    path.add(float(h @ (lin.x - fwd.fem.x_rest)), lin.x, float(lin.lam[0]), col[2] / s, 1.0 / s)
    return col


def _sweep(model, config: EstimatorConfig, acfg: AtlasConfig, i: int, l: int, only=None, seed=None):
    """One task: the (f_y, f_z) plane at grid f_x index ``i`` and pressure index ``l`` (with
    ``acfg.linear_pressure``: at the pressure range's middle, ``l`` ignored). The point
    nearest zero load is reached from rest by continuation, every other one from a converged inner
    neighbour (one grid step nearer zero load): a predictor on the neighbour's sensitivities,
    chord iterations with the neighbour's last factor (kept until the points solved from it are
    done, :func:`_plane_walk`), a refactorization where they stall, Newton where they fail
    (:meth:`~softphantom.estimation.linearization.EquilibriumSolver.solve`). A point whose
    inner neighbour did not converge is
    not tried: reachability is taken to be monotone in the load, so a failure does not cost the
    (slow) failing solves of everything beyond it. Expected solver failures are recorded, not
    raised (a displacement axis's planes at its f_x faces are solved here; the points between by
    :func:`_lines`). Returns (i, l,
    V (ny,nz,n_arms), P (ny,nz,k,3), X (ny,nz,3N) displacements, solved (ny,nz), first failure message
    or '', CPU seconds of this process, the derivatives (dV, dP, dX) of the same shapes per Pa along
    the pressure (``linear_pressure``) or per unit load along ``acfg.hermite_axis``
    (:func:`_axis_derivative`, with dFX (ny,nz)), or None, FX (ny,nz) the points' f_x N, Q (ny,nz)
    their first coordinate (the node), the number
    of converged forward solves); unsolved entries are NaN.

    A segment of the plane (a task of a finer graph, :func:`_face_part`): ``only`` the (j, k)
    points to solve, walked in the plane's order; ``seed`` ((j, k), displacements (3N,) m) a point
    another task solved, linearized where it is (one factorization) and the start of the points
    walked from it. A point is tried when its inner neighbours within the segment converged."""
    t0 = time.process_time()
    fwd = _task_forward(model, config, acfg)
    ax = acfg.axes()
    ny, nz = len(ax[1]), len(ax[2])
    linear = acfg.linear_pressure
    hermite = acfg.hermite_axis
    p_u = 0.5 * (ax[3][0] + ax[3][-1]) if linear else ax[3][l]
    V = np.full((ny, nz, len(fwd.eq.arm_names)), np.nan)
    P = np.full((ny, nz, fwd.probe.shape[0], 3), np.nan)
    X = np.full((ny, nz, fwd.fem.n_dof), np.nan)
    deriv = linear or hermite is not None
    dV, dP, dX = (np.full_like(a, np.nan) for a in (V, P, X)) if deriv else (None, None, None)
    dFX = np.full((ny, nz), np.nan)
    h = x_patch(fwd) if acfg.x_control == "displacement" else None
    solved = np.zeros((ny, nz), bool)
    FX = np.full((ny, nz), np.nan)
    n_solves = 0
    Q = np.full((ny, nz), ax[0][i])
    centre = (int(np.argmin(np.abs(ax[1]))), int(np.argmin(np.abs(ax[2]))))
    lins: dict[tuple[int, int], object] = {}
    kept: dict[tuple[int, int], object] = {}  # factors of solved points with points still to solve from them
    left: dict[tuple[int, int], int] = {}
    last = None  # the point whose factor the solver holds
    first_error = ""
    walk = _plane_walk(ny, nz, *centre)
    mine = None
    if only is not None:
        mine = {tuple(q) for q in only} | ({tuple(seed[0])} if seed is not None else set())
        walk = _sub_walk(walk, mine)
    for p, parent, n_kids in walk:
        if parent in left:
            left[parent] -= 1
        reachable = all(q in lins for q in _inner(p, centre) if mine is None or q in mine)
        if reachable and parent is not None and last != parent:
            fwd.eq.restore(kept[parent])
        if parent in left and left[parent] == 0:
            kept.pop(parent, None)  # its last child: the copy (28 MB at 6 mm) is not needed any more
        if not reachable:
            continue  # beyond a failure: unreachable (see the docstring)
        j, k = p
        lam = np.array([ax[0][i], ax[1][j], ax[2][k], p_u])
        last = None
        if seed is not None and p == tuple(seed[0]):  # solved by another task: the start of this segment
            if seed[1] is None:
                continue
            lins[p] = _linearized_at(fwd, fwd.fem.x_rest + seed[1], lam)
            last = p
            if n_kids > 1:
                kept[p] = fwd.eq.keep()
            left[p] = n_kids
            continue
        try:
            # a linear pressure axis needs the exact pressure derivative: the tangent at the solution
            # (elsewhere a new factor there costs more than the chord iterations it saves)
            lin = fwd.solve(lam, lins.get(parent), factor_at_solution=linear, via_tol=VIA_TOL)
        except SolverError as exc:
            first_error = first_error or str(exc).splitlines()[0]
            continue
        last = p
        n_solves += 1
        if n_kids > 1:
            kept[p] = fwd.eq.keep()
        left[p] = n_kids
        lins[p] = lin
        solved[j, k] = True
        FX[j, k] = lin.lam[0]
        V[j, k] = lin.V
        P[j, k] = lin.sub_x
        X[j, k] = lin.x - fwd.fem.x_rest
        if linear:
            dV[j, k] = lin.W[:, 3]
            dP[j, k] = lin.sub_U[:, :, 3]
            dX[j, k] = lin.U[:, 3]
        elif hermite is not None:  # exact at the solution: GMRES on its tangent, the kept factor preconditioning
            dV[j, k], dP[j, k], dX[j, k], dFX[j, k] = _axis_derivative(fwd, lin, hermite, h if hermite == 0 else None)
    return (i, l, V, P, X, solved, first_error, time.process_time() - t0, (dV, dP, dX, dFX) if deriv else None, FX,
            Q, n_solves)


def _lines(model, config: EstimatorConfig, acfg: AtlasConfig, k: int, l: int, ends, starts, dends=None):
    """One task of a displacement axis's inner points: the lines along q at f_z index ``k`` and
    pressure index ``l``, each walked from its lower f_x face to the upper one. ``ends`` (ny,) × 2:
    the faces' patch displacements (m; NaN: unsolved) at (·, k, l). A line starts at its lower face
    point, ``starts`` (ny, 3N): the displacements the face plane solved there (:func:`_sweep`),
    linearized where they are (one factorization, no solve). Each next point is solved at the
    displacement of its q from the point before it (:func:`_solve_ux`: one mixed-control solve,
    its predictor the cubic Hermite through the last two along the line, :class:`LinePredictor`,
    from their exact derivatives along ū) — one small step of the state each, where a plane at
    fixed q (:func:`_sweep`) crosses the arm pair's step in f_x from a neighbour in f_y. Returns
    (k, l, V (n1−2, ny, n_arms), P (n1−2, ny, k, 3), X
    (n1−2, ny, 3N), solved (n1−2, ny), first failure or '', CPU seconds, FX (n1−2, ny), Q (n1−2, ny),
    converged forward solves, the derivatives along the Hermite axis (dV, dP, dX, dFX) of the same
    shapes or None: along ū (``acfg.hermite_axis`` 0), or along another load at fixed q, for which
    ``dends`` (ny,) × 2 are the faces' dū/dλ_a (:func:`_axis_derivative`))."""
    t0 = time.process_time()
    fwd = _task_forward(model, config, acfg)
    ax = acfg.axes()
    n1, ny = len(ax[0]), len(ax[1])
    h = x_patch(fwd)
    lo, hi = ax[0][0], ax[0][-1]
    span = hi - lo
    fz, p_u = ax[2][k], ax[3][l]
    m = n1 - 2
    V = np.full((m, ny, len(fwd.eq.arm_names)), np.nan)
    P = np.full((m, ny, fwd.probe.shape[0], 3), np.nan)
    X = np.full((m, ny, fwd.fem.n_dof), np.nan)
    FX = np.full((m, ny), np.nan)
    Q = np.broadcast_to(ax[0][1:-1, None], (m, ny)).copy()
    solved = np.zeros((m, ny), bool)
    hermite = acfg.hermite_axis is not None
    if hermite:  # the derivatives along the axis: arrays as large as the values, only when asked for
        dV, dP, dX, dFX = (np.full_like(a, np.nan) for a in (V, P, X, FX))
    first_error, n_solves = "", 0
    for j in range(ny):
        u0, u1 = float(ends[0][j]), float(ends[1][j])
        if not (np.isfinite(u0) and np.isfinite(u1)):
            continue  # a face unsolved: beyond the reachable region
        try:
            # the face plane's equilibrium: its tangent, not a solve again
            lin = _linearized_at(fwd, fwd.fem.x_rest + starts[j], np.array([lo, ax[1][j], fz, p_u]))
            before = None  # the point before the last on the line
            path = LinePredictor()
            _line_knot(fwd, h, lin, path)
            for i in range(1, n1 - 1):
                target = u0 + (ax[0][i] - lo) / span * (u1 - u0)
                gap = min(ax[0][i] - ax[0][i - 1], ax[0][i + 1] - ax[0][i])
                u = float(h @ (lin.x - fwd.fem.x_rest))
                u_b = float(h @ (before.x - fwd.fem.x_rest)) if before is not None else u
                if u != u_b and lin.lam[0] != before.lam[0]:  # the secant along the line
                    d = (u - u_b) / (lin.lam[0] - before.lam[0])
                else:
                    d = float(h @ lin.U[:, 0])
                guess = lin.lam[0] + (target - u) / d if d > 0 else lin.lam[0]
                lam = np.array([guess, ax[1][j], fz, p_u])
                start = lin
                lin, n = _solve_ux(fwd, h, lam, target, start, (start.lam[0], hi), NODE_TOL * gap / span * abs(u1 - u0),
                                   prev=before, fx_range=(lo, hi), predictor=path if path.knots else None)
                col0 = _line_knot(fwd, h, lin, path)
                before = start
                n_solves += n
                a = i - 1
                solved[a, j] = True
                V[a, j], P[a, j], X[a, j] = lin.V, lin.sub_x, lin.x - fwd.fem.x_rest
                FX[a, j] = lin.lam[0]
                Q[a, j] = lo + span * (float(h @ (lin.x - fwd.fem.x_rest)) - u0) / (u1 - u0)
                if hermite:
                    t = (float(h @ (lin.x - fwd.fem.x_rest)) - u0) / (u1 - u0)
                    du_q = None if dends is None else (1 - t) * float(dends[0][j]) + t * float(dends[1][j])
                    dV[a, j], dP[a, j], dX[a, j], dFX[a, j] = _axis_derivative(fwd, lin, acfg.hermite_axis, h, du_q,
                                                                               col0)
        except SolverError as exc:
            first_error = first_error or str(exc).splitlines()[0]
    return (k, l, V, P, X, solved, first_error, time.process_time() - t0, FX, Q, n_solves,
            (dV, dP, dX, dFX) if hermite else None)


@dataclass
class GridPart:
    """What one task of a build's fine graph solved (:func:`_face_part`, :func:`_line_task`): at the
    grid points ``idx`` (n, 4) (i, j, k, l) the volumes ``V`` (n, n_arms), tracked points ``P``
    (n, k, 3), displacements ``X`` (n, 3N), f_x ``FX`` (n,), first coordinate ``Q`` (n,),
    ``solved`` (n,) (unsolved rows NaN) and ``derivs`` (dV, dP, dX, dFX) along the Hermite axis or
    None; the first failure (``error``), the CPU seconds and the converged forward solves."""

    idx: np.ndarray
    V: np.ndarray
    P: np.ndarray
    X: np.ndarray
    FX: np.ndarray
    Q: np.ndarray
    solved: np.ndarray
    derivs: tuple | None
    error: str
    cpu_s: float
    n_solves: int

    def row(self, j: int, k: int) -> int:
        """The row of grid point (·, j, k, ·)."""
        return int(np.flatnonzero((self.idx[:, 1] == j) & (self.idx[:, 2] == k))[0])


def face_segments(acfg: AtlasConfig) -> list[tuple[str, list[tuple[int, int]]]]:
    """A face plane's walk (:func:`_plane_walk`) as segments, each a task: ``("spine", points)``,
    the spine along f_z through the point nearest zero load (solved from rest), then
    ``("branch-k", points)`` for each f_z index k, the points along f_y from spine point (j0, k),
    which seeds it.

    >>> [(n, len(p)) for n, p in face_segments(AtlasConfig(n_force=(3, 4, 3)))]
    [('spine', 3), ('branch-0', 3), ('branch-1', 3), ('branch-2', 3)]
    """
    ax = acfg.axes()
    ny, nz = len(ax[1]), len(ax[2])
    j0 = int(np.argmin(np.abs(ax[1])))
    out = [("spine", [(j0, k) for k in range(nz)])]
    out += [(f"branch-{k}", [(j, k) for j in range(ny) if j != j0]) for k in range(nz)]
    return out


def _face_part(model, config: EstimatorConfig, acfg: AtlasConfig, i: int, l: int, points, seed=None) -> GridPart:
    """One segment of a face plane (:func:`face_segments`) by :func:`_sweep`: the ``points`` (j, k),
    from rest or from ``seed`` ((j0, k), its displacements or None: unsolved, and so are these)."""
    got = _sweep(model, config, acfg, i, l, only=points, seed=seed)
    _, _, V, P, X, solved, err, cpu, deriv, FX, Q, n = got
    js, ks = (np.array(v, dtype=np.int64) for v in zip(*points))
    idx = np.stack([np.full_like(js, i), js, ks, np.full_like(js, l)], axis=1)
    return GridPart(idx, V[js, ks], P[js, ks], X[js, ks], FX[js, ks], Q[js, ks], solved[js, ks],
                    None if deriv is None else tuple(d[js, ks] for d in deriv), err, cpu, n)


def _line_task(model, config: EstimatorConfig, acfg: AtlasConfig, k: int, l: int, j: int, ends, start,
               dends=None) -> GridPart:
    """One line along q (f_y index ``j``, f_z ``k``, pressure ``l``) between its two face points by
    :func:`_lines`: ``ends`` (2,) their patch displacements (m, NaN: unsolved), ``start`` (3N,) the
    lower face point's displacements, ``dends`` (2,) their dū/dλ_a on a Hermite axis a ≠ 0."""
    ny = acfg.shape[1]

    def one(v):
        a = np.full(ny, np.nan)
        a[j] = v
        return a

    starts = np.zeros((ny, len(start)))
    starts[j] = start
    got = _lines(model, config, acfg, k, l, tuple(one(e) for e in ends), starts,
                 None if dends is None else tuple(one(d) for d in dends))
    _, _, V, P, X, solved, err, cpu, FX, Q, n, deriv = got
    m = V.shape[0]
    idx = np.stack([np.arange(1, m + 1), np.full(m, j), np.full(m, k), np.full(m, l)], axis=1)
    return GridPart(idx, V[:, j], P[:, j], X[:, j], FX[:, j], Q[:, j], solved[:, j],
                    None if deriv is None else tuple(d[:, j] for d in deriv), err, cpu, n)


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
