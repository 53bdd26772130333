"""What one task of an atlas build solves (estimation/atlas/build.py puts the tasks
together): on a force axis one (f_y, f_z) plane of the grid walked outwards from zero load, each
point from a converged neighbour (:func:`_sweep`); on a displacement-controlled first axis a
segment of a face plane (:func:`_face_part`) or one line along q between its two face points
(:func:`_line_task`, one mixed-control solve a point, :func:`_solve_ux`). Each task solves with its
own forward model (:func:`_task_forward`), so its result does not depend on the worker.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from softphantom.errors import SolverError, UserError
from softphantom.estimation.atlas.config import FALLBACK_MIN_LOAD_STEP, NODE_TOL, VIA_TOL, AtlasConfig, x_patch
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
