"""Ground truth of the virtual phantom, from a model of higher fidelity than the estimator's.

The estimator's model is the design meshed at ``h`` (mm) with its own laws and element order and
a fast per-sample update. The truth differs from it in form, not only in mesh: the same design
with quadratic 10-node tetrahedra (``order = 2``, the default: curved walls, no volumetric locking
at ν = 0.45; docs/model.md) whose node spacing is ``mesh_scale`` (0.75 by default) times the
model's, i.e. elements of ``order · mesh_scale · h`` for a linear model (9 mm for a 6 mm one: a
10-node tet has a node at each edge's middle, so it has the node spacing of a linear tet half its
size) and of ``mesh_scale · h`` for a quadratic one (6.75 mm for the default 9 mm model),
every co-rotational region replaced by its hyperelastic twin (compressible neo-Hookean with the
same E, ν: ``law = "neo-hookean"``, the default; ``"model"`` keeps the design's laws), solved to
convergence by Newton (relative residual 1e-8) with the load on a contact patch
(``patch_radius_mm``), so an estimate is never checked against its own model (DESIGN.md §5).

Quasi-static and elastic, the state depends only on the load, not on its history. Each event of a
scenario is a one-parameter load path from rest (level s times its peak), so the truth is solved
at a few *keyframes in load*, s = 1/L … 1 (warm-started continuation: each solve starts from the
previous level's state), and every output is interpolated in s by a monotone cubic (PCHIP, exact at
the keyframes), then mapped to time through the event's level s(t). A hold or a release revisits
states already solved, so they cost nothing. An inflation "until the target moves N mm" marches
the pressure up in steps of ``max_p/10`` and finds the pressure by a secant step between the last
two keyframes (one more solve), or stops at ``max_p_kPa``. An inflation loads one internal cavity
(its event's ``cavity``); the truth records every cavity's pressure and volume change.

A repeated event (``repeat``, ``period_s``) revisits the same path: no more solves. Two events
acting at once (a *group*, :attr:`~softphantom.virtual.scenario.Scenario.groups`: a push during an
inflation, two pushes, two inflations) load the phantom together, their loads added (forces at
their points, pressures in their cavities): a two-parameter load path. Its keyframes are the tensor
grid of the two levels (s1_i, s2_j), i, j = 0 … L; the edges s2 = 0 and s1 = 0 are the two events'
own keyframes, so a group costs L² more solves, row by row, each from the bilinear predictor of its
three solved neighbours x(i−1, j) + x(i, j−1) − x(i−1, j−1). Every output is interpolated by
tensor-product PCHIP (along s1, then along s2) and sampled at (s1(t), s2(t)); where one of the two
rests, that is its partner's own truth exactly.

What a solved truth holds is in virtual/truth_records.py, the cache of solved truths in
virtual/truth_cache.py; this module re-exports their names.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time

import numpy as np

from softphantom.design import PhantomModel, build_model
from softphantom.errors import DesignError, MeshError, SolverError
from softphantom.fem import (
    ElementInversionError,
    cavity_volume,
    fem_from_phantom,
    force_actuator,
    probe_matrix,
    solve_static,
)
from softphantom.progress import report
from softphantom.virtual.scenario import Event, Scenario
from softphantom.virtual.truth_cache import (  # the cache, re-exported
    CACHE_ENV, TRUTH_CACHE_FORMAT, load_truth, save_truth, truth_cache_dir, truth_key)
from softphantom.virtual.truth_records import (  # the records, re-exported
    TRUTH_LAWS, EventTruth, GroupTruth, Truth, TruthConfig, TruthSamples, pchip_rows, truth_laws)

__all__ = ["CACHE_ENV", "TRUTH_CACHE_FORMAT", "TRUTH_LAWS", "EventTruth", "GroupTruth", "Truth", "TruthConfig",
           "TruthSamples", "load_truth", "pchip_rows", "save_truth", "solve_truth", "truth_cache_dir", "truth_key",
           "truth_laws", "truth_model", "write_snapshot"]

log = logging.getLogger(__name__)


def truth_model(model: PhantomModel, config: TruthConfig = TruthConfig()) -> PhantomModel:
    """The design of ``model`` meshed with elements of ``config.order`` and a node spacing
    ``config.mesh_scale`` times the model's (its element size over its element order): for a
    linear model of size h, elements of ``order · mesh_scale · h``; for a quadratic one, of
    ``order · mesh_scale · h / 2``, so the truth is finer than the model of either order."""
    design = model.design
    spacing_mm = design.mesh.size_mm / design.mesh.element_order
    if design.mesh.element_order != config.order:
        design = dataclasses.replace(design, mesh=dataclasses.replace(design.mesh, element_order=config.order))
    size_mm = spacing_mm * config.mesh_scale * config.order
    try:
        return build_model(design, size_mm)
    except (DesignError, MeshError) as exc:
        # the mesher's hint names `design`'s options; say what the virtual commands can change
        msg, coarser = str(exc), "a coarser --mesh-size-mm" in str(exc)
        # design's own hint, the last parenthesis (or its last clause) ending in "--force"
        msg = re.sub(r"; [^;()]*--force\)$", ")", re.sub(r" \([^()]*--force\)$", "", msg))
        what = ("a larger --truth-mesh-scale (up to 1), or a model designed with a coarser --mesh-size-mm" if coarser
                else "a smaller --truth-mesh-scale or --truth-order 1 (or a model designed with a finer --mesh-size-mm)")
        raise type(exc)(f"truth mesh (P{config.order}, {size_mm:.3g} mm elements for node spacing "
                        f"{config.mesh_scale:g} x the model's {spacing_mm:g} mm): {msg}; use {what}") from None


def _patch_radius(fem, point: np.ndarray, radius_m: float) -> float:
    """``radius_m``, widened until the patch holds at least 3 surface nodes (coarse meshes)."""
    surf = np.unique(fem.boundary_faces)
    d = np.sort(np.linalg.norm(fem.nodes[surf] - point, axis=1))
    return max(radius_m, float(d[2]) * 1.001)


def solve_truth(scenario: Scenario, model: PhantomModel, config: TruthConfig = TruthConfig(),
                truth_mesh: PhantomModel | None = None, *, cache: bool = False) -> Truth:
    """Solve the truth of ``scenario`` (see the module docstring). ``model`` is the estimator's
    model (its design and mesh size set the truth mesh), or pass ``truth_mesh`` directly.
    Its progress is reported as it starts and after each keyframe, with the time left (task
    ``<scenario>: truth``, done/total keyframes, :func:`softphantom.progress.report`); a given
    ``truth_mesh`` sets the element order (its own). ``cache``: read the truth from the truth
    cache (:func:`truth_cache_dir`) when it holds this one, and keep it there once solved."""
    scenario = _checked(scenario, model if truth_mesh is None else truth_mesh)
    where = truth_cache_dir() if cache else None
    if where is None:
        return _solve_truth(scenario, model, config, truth_mesh)
    key = truth_key(scenario, model, config, truth_mesh)
    entry = where / "truth" / key[:32]
    found = load_truth(entry, scenario, config)
    if found is not None:
        log.info("%s: truth from the cache (%s; solved in %.1f s)", scenario.name, entry, found.solve_s)
        return found
    truth = _solve_truth(scenario, model, config, truth_mesh)
    save_truth(truth, entry, key)
    return truth


def _checked(scenario: Scenario, given: PhantomModel) -> Scenario:
    """The scenario checked against the model (its contact points and cavities), each inflation's
    cavity named: before the truth is meshed."""
    scenario.check_points(given.p_ext)
    measured = given.design.measured_cavity_names
    for e in scenario.events:
        if e.kind == "inflate" and e.cavity in measured:
            from softphantom.virtual.scenario import ScenarioError

            raise ScenarioError(f"{scenario.source}: inflate.cavity {e.cavity}: a measured cavity (read as a volume, "
                                f"never loaded); the actuated ones: {', '.join(given.design.pressure_names) or 'none'}")
    return scenario.check_cavities(given.design.pressure_names)


def _solve_truth(scenario: Scenario, model: PhantomModel, config: TruthConfig,
                 truth_mesh: PhantomModel | None) -> Truth:
    return _TruthSolve(scenario, model, config, truth_mesh).run()


class _TruthSolve:
    """One solve of a scenario's truth, in named steps: :meth:`__init__` meshes the truth model and
    reads its rest state, :meth:`run` solves each event's keyframes (:meth:`level_path` for a push
    or an inflation to a pressure, :meth:`inflate_to_target` for one until a target moves), then
    each group's (:meth:`solve_group`), reporting progress after every solve."""

    def __init__(self, scenario: Scenario, model: PhantomModel, config: TruthConfig,
                 truth_mesh: PhantomModel | None) -> None:
        self.t0 = time.perf_counter()
        self.scenario, self.config = scenario, config
        self.task = f"{scenario.name}: truth"
        if truth_mesh is None:
            report(log, self.task, 0, None, "meshing the truth model")
        tm = self.tm = truth_mesh if truth_mesh is not None else truth_model(model, config)
        self.t_mesh = time.perf_counter()
        laws = truth_laws(tm, config.law)
        fem = self.fem = fem_from_phantom(tm, laws)  # the truth mesh's element order
        self.marker_names = tuple(tm.markers)
        self.target_names = tuple(tm.targets)
        self.P = probe_matrix(fem, np.vstack([[tm.markers[k] for k in self.marker_names],
                                              [tm.targets[k] for k in self.target_names]]))
        self.x_rest = x_rest = fem.nodes.copy()
        # the points as the mesh carries them at rest (a marker on the curved surface sits up to a
        # fraction of a mm off the faceted mesh surface): motion relative to rest is then exact
        carried = self.P @ x_rest
        self.rest_markers, self.rest_targets = carried[: len(self.marker_names)], carried[len(self.marker_names):]
        # the surfaces of the element order (6-node triangles on a quadratic mesh: curved walls)
        self.closed = np.vstack([tm.outer_faces6, tm.fixed_faces6] if tm.element_order == 2
                                else [tm.outer_faces, tm.fixed_faces])
        self.cavities = tm.design.cavity_names  # the arms in the sensor order, then the internal cavities
        self.V0 = np.array([cavity_volume(x_rest, fem.cavities[c]) for c in self.cavities])
        self.bulb0 = cavity_volume(x_rest, self.closed)
        self.k = len(self.marker_names)
        self.total = self._count_keyframes()
        self.grouped = {i for pair in scenario.groups for i in pair}
        self.paths: dict[int, list] = {}  # event index in a group -> its states at the keyframes (the group's edges)
        self.done = 0
        self.actuators: dict[str, object] = {}

    def _count_keyframes(self) -> int:
        """The solves the scenario takes (an inflation to a target: its steps); refuses such an
        inflation in a group."""
        scenario, config = self.scenario, self.config
        total = sum(config.levels if e.kind == "push" or e.p_kPa is not None else config.inflate_steps
                    for e in scenario.events)
        total += config.levels**2 * len(scenario.groups)  # a group's inner keyframes
        for pair in scenario.groups:
            for i in pair:
                if scenario.events[i].kind == "inflate" and scenario.events[i].p_kPa is None:
                    from softphantom.virtual.scenario import ScenarioError

                    raise ScenarioError(f"{scenario.source}: inflate.target_shift_mm: an inflation until a target "
                                        f"moves cannot overlap another event; give p_kPa")
        return total

    def run(self) -> Truth:
        report(log, self.task, 0, self.total,
               f"P{self.tm.element_order} truth mesh of {len(self.tm.nodes)} nodes: solving keyframe 1")
        self.events = []
        for i, e in enumerate(self.scenario.events):
            self.events.append(self.solve_event(i, e))
        group_truths = tuple(self.solve_group(n, pair) for n, pair in enumerate(self.scenario.groups))
        return Truth(self.scenario, self.tm, self.marker_names, self.target_names, self.rest_markers, self.V0,
                     tuple(self.events), time.perf_counter() - self.t0, self.config, group_truths)

    def progress(self, what: str) -> None:
        """One keyframe more, with the time left at the mean time a keyframe has taken so far."""
        done, total = self.done, self.total
        spent = time.perf_counter() - self.t_mesh
        left = spent / done * (total - done) if done else 0.0
        eta = f"; ETA {_clock(left)}" if done < total else ""
        report(log, self.task, done, total, f"{what}{eta}")

    def actuator(self, point: str):
        """The force actuator of the contact patch at ``point``, made once (every keyframe of its
        events and groups uses it)."""
        if point not in self.actuators:
            pt = self.tm.p_ext[point]
            self.actuators[point] = force_actuator(
                self.fem, pt, radius=_patch_radius(self.fem, pt, self.scenario.patch_radius_mm * 1e-3))
        return self.actuators[point]

    def readout(self, x):
        """(cavity volume changes, markers, target shifts, bulb volume change) of the state ``x``."""
        x = np.asarray(x).reshape(-1, 3)
        pts = self.P @ x
        dv = np.array([cavity_volume(x, self.fem.cavities[c]) for c in self.cavities]) - self.V0
        return dv, pts[:self.k], pts[self.k:] - self.rest_targets, cavity_volume(x, self.closed) - self.bulb0

    def solve(self, f_ext, p, cavity, x0, what, x_prev=None, ratio=1.0, min_step=1.0 / 64, max_iter=25,
              single=False):
        """Converged equilibrium under ``f_ext`` and the pressure ``p`` in ``cavity``; warm start from
        ``x0``, or the secant predictor x0 + ratio·(x0 − x_prev) when the previous keyframe is known
        (falls back to x0).

        From the predictor, one Newton at the full load, stepping on through a tangent that is not
        positive definite with the shifted Cholesky (``on_indefinite="shift"``): a cut load step
        restarts the load from zero while the state is near the full load's (the urethra's target
        solves then collapsed the cavity and took the exact LDLᵀ step, 16 s a factorization on the
        default P2 truth, 64 s a solve; shifted: 4 iterations, 4 s)."""
        fem, config = self.fem, self.config
        sol = None
        if x_prev is not None:
            try:
                sol = solve_static(fem, f_ext, pressures={cavity: p} if p else None,
                                   x0=x0 + ratio * (x0 - x_prev), tol=config.tol, min_load_step=1.0,
                                   max_iter=max_iter, on_indefinite="shift")
            except ElementInversionError:
                sol = None
            if sol is not None and not sol.converged:
                sol = None
                if single:
                    raise SolverError(f"truth of {self.scenario.name}: {what}: no convergence from the predictor")
        if sol is None:
            sol = solve_static(fem, f_ext, pressures={cavity: p} if p else None, x0=x0, tol=config.tol,
                               min_load_step=min_step, max_iter=max_iter)
        if not sol.converged:
            raise SolverError(f"truth of {self.scenario.name}: {what}: {sol.status}")
        self.done += 1
        self.progress(what)
        return sol

    def solve_event(self, i: int, e: Event) -> EventTruth:
        """The truth of event ``i`` alone, at its keyframes from rest."""
        if e.kind == "push":
            H = self.actuator(e.point)
            f = np.asarray(e.force_N, float)
            s_list, rows, x, its = self.level_path(
                i, lambda s: (H @ (s * f), 0.0), lambda s: f"event {i + 1} push {s:.2f}·{np.round(f, 2).tolist()} N",
                e.cavity)
            force, p_peak, note = f, 0.0, ""
        elif e.p_kPa is not None:
            p_peak = e.p_kPa * 1e3
            s_list, rows, x, its = self.level_path(
                i, lambda s: (None, s * p_peak), lambda s: f"event {i + 1} inflate {s * p_peak / 1e3:.1f} kPa",
                e.cavity)
            force, note = np.zeros(3), ""
        else:
            s_list, rows, x, its, p_peak, note = self.inflate_to_target(i, e)
            force = np.zeros(3)
        dv, mk, tg, bulb = (np.array(v) for v in zip(*rows))
        return EventTruth(e, np.asarray(s_list), dv, mk, tg, bulb, force, float(p_peak),
                          np.asarray(x).reshape(-1, 3).copy(), its, note)

    def level_path(self, i: int, load, label, cavity):
        """Keyframes at the levels s = 1/L … 1 of event ``i``, whose load at level s is
        ``load(s)`` = (nodal forces or None, pressure in ``cavity``), each from the secant
        predictor of the two before: (levels, readouts, last state, Newton iterations). A grouped
        event's states are kept in :attr:`paths` (its group's edge)."""
        config, x_rest = self.config, self.x_rest
        rows = [self.readout(x_rest)]
        s_list = [0.0]
        x = x_rest.reshape(-1)
        its = 0
        x_prev = None
        for lv in range(1, config.levels + 1):
            s = lv / config.levels
            f_ext, p = load(s)
            sol = self.solve(f_ext, p, cavity, x, label(s), x_prev)
            x_prev, x, its = x, sol.x.reshape(-1), its + sol.iterations
            rows.append(self.readout(x))
            s_list.append(s)
            if i in self.grouped:
                self.paths.setdefault(i, [x_rest.reshape(-1)]).append(x)
        return s_list, rows, x, its

    def inflate_to_target(self, i: int, e: Event):
        """An inflation of event ``i`` until its target moves ``target_shift_mm``: the pressure
        marched up in steps, then the pressure of the goal found between the last two keyframes
        (:meth:`_pressure_of_goal`), or stopped at ``max_p_kPa``: (levels, readouts, last state,
        Newton iterations, peak pressure, note)."""
        scenario, config, target_names = self.scenario, self.config, self.target_names
        cavity = e.cavity
        rows = [self.readout(self.x_rest)]
        its = 0
        note = ""
        j = target_names.index(e.target) if e.target in target_names else None
        if j is None:
            from softphantom.virtual.scenario import ScenarioError

            raise ScenarioError(f"{scenario.source}: inflate.target {e.target!r} is not a target of the "
                                f"design ({', '.join(target_names)})")
        goal = e.target_shift_mm * 1e-3
        pmax = e.max_p_kPa * 1e3
        step = pmax / config.inflate_steps
        min_step = step / 2
        ps, shifts, xs = [0.0], [0.0], [self.x_rest.reshape(-1)]
        p_star = None
        while ps[-1] < pmax - 1e-9:
            # continuation in pressure: one Newton attempt per increment (secant predictor, then
            # from the last state; 6 iterations), halving the increment once on failure; a second
            # failure means a limit point of the model (the cavity runs away)
            p = min(pmax, ps[-1] + step)
            try:
                prev = xs[-2] if len(xs) > 1 else None
                ratio = (p - ps[-1]) / (ps[-1] - ps[-2]) if len(xs) > 1 else 1.0
                sol = self.solve(None, p, cavity, xs[-1], f"event {i + 1} inflate {p / 1e3:.1f} kPa", prev, ratio,
                                 min_step=1.0, max_iter=6, single=True)
            except SolverError as exc:
                if step / 2 >= min_step - 1e-9:
                    step /= 2
                    continue
                note = (f"limit: the model's pressure maximum is near {ps[-1] / 1e3:.1f} kPa (no equilibrium at "
                        f"{p / 1e3:.1f} kPa: {str(exc).split(': ')[-1]})")
                break
            its += sol.iterations
            r = self.readout(sol.x)
            ps.append(p)
            shifts.append(float(np.linalg.norm(r[2][j])))
            xs.append(sol.x.reshape(-1))
            rows.append(r)
            if shifts[-1] >= goal:
                # secant between the last two keyframes, then one solve there
                a, b = shifts[-2], shifts[-1]
                p_star = ps[-2] + (goal - a) / (b - a) * (ps[-1] - ps[-2])
                break
        if p_star is not None:
            more, sh = self._pressure_of_goal(i, e, j, goal, p_star, ps, shifts, xs, rows)
            its += more
            note = note or f"{e.target} moved {sh * 1e3:.2f} mm at {ps[-1] / 1e3:.1f} kPa"
        elif not note:
            key = "max_p_urethra_kPa" if cavity == "urethra" else "max_p_kPa"
            note = f"limit: {e.target} moved only {shifts[-1] * 1e3:.2f} mm at {key} {pmax / 1e3:g}"
        if len(ps) < 2:
            raise SolverError(f"truth of {scenario.name}: inflation failed at the first step ({note})")
        p_peak = ps[-1]
        return list(np.asarray(ps) / p_peak), rows, xs[-1], its, p_peak, note

    def _pressure_of_goal(self, i, e, j, goal, p_star, ps, shifts, xs, rows) -> tuple[int, float]:
        """Regula falsi on the bracket (last keyframe below the goal, the one above), at most 4
        solves, until the target's shift is within 0.5 % of the goal; the bracket's top keyframe is
        replaced by the solve found (in ``ps``, ``xs``, ``rows``). Returns the Newton iterations it
        took and the target's shift found."""
        its = 0
        lo_p, lo_s = ps[-2], shifts[-2]
        hi_p, hi_s = ps[-1], shifts[-1]
        for lst in (ps, shifts, xs, rows):
            lst.pop()
        for _ in range(4):
            prev = xs[-2] if len(xs) > 1 else None
            ratio = (p_star - ps[-1]) / (ps[-1] - ps[-2]) if len(xs) > 1 else 1.0
            sol = self.solve(None, p_star, e.cavity, xs[-1], f"event {i + 1} inflate {p_star / 1e3:.1f} kPa (target)",
                             prev, ratio)
            its += sol.iterations
            r = self.readout(sol.x)
            sh, p_solved = float(np.linalg.norm(r[2][j])), p_star
            if abs(sh - goal) <= 0.005 * goal:
                break
            if sh < goal:
                lo_p, lo_s = p_star, sh
            else:
                hi_p, hi_s = p_star, sh
            p_star = lo_p + (goal - lo_s) / (hi_s - lo_s) * (hi_p - lo_p)
        ps.append(float(p_solved))
        xs.append(sol.x.reshape(-1))
        rows.append(r)
        return its, sh

    def loads(self, e: Event, s: float):
        """The nodal forces (or None) and cavity pressures of event ``e`` at level ``s``."""
        if e.kind == "push":
            return self.actuator(e.point) @ (s * np.asarray(e.force_N, float)), {}
        return None, {e.cavity: s * e.p_kPa * 1e3}

    def solve_group(self, n: int, pair: tuple[int, int]) -> GroupTruth:
        """The truth of group ``n`` (two events at once) on the tensor grid of their levels: its
        edges the two events' own keyframes, its inside solved row by row (:meth:`_group_keyframe`)."""
        e1, e2 = (self.scenario.events[i] for i in pair)
        L = self.config.levels
        lv = np.arange(L + 1) / L
        X = [[None] * (L + 1) for _ in range(L + 1)]
        grid = [[None] * (L + 1) for _ in range(L + 1)]
        for k in range(L + 1):  # the edges: each event alone
            X[k][0], X[0][k] = self.paths[pair[0]][k], self.paths[pair[1]][k]
            et1, et2 = self.events[pair[0]], self.events[pair[1]]
            grid[k][0] = (et1.dV[k], et1.markers[k], et1.targets[k], et1.bulb_dV[k])
            grid[0][k] = (et2.dV[k], et2.markers[k], et2.targets[k], et2.bulb_dV[k])
        its = 0
        for i in range(1, L + 1):
            for j in range(1, L + 1):
                what = (f"group {n + 1} ({e1.kind} + {e2.kind}) keyframe {(i - 1) * L + j}/{L * L} at levels "
                        f"({lv[i]:.2f}, {lv[j]:.2f})")
                sol = self._group_keyframe(e1, e2, lv[i], lv[j], X[i - 1][j] + X[i][j - 1] - X[i - 1][j - 1],
                                           X[i][j - 1], what)
                its += sol.iterations
                X[i][j] = sol.x.reshape(-1)
                grid[i][j] = self.readout(X[i][j])
                self.done += 1
                self.progress(what)
        dv, mk, tg, bulb = (np.array([[np.asarray(c[q]) for c in row] for row in grid]) for q in range(4))
        force = sum((np.asarray(e.force_N, float) for e in (e1, e2) if e.kind == "push"), np.zeros(3))
        peak = {}
        for e in (e1, e2):
            if e.kind == "inflate":
                peak[e.cavity] = peak.get(e.cavity, 0.0) + e.p_kPa * 1e3
        return GroupTruth(pair, (e1, e2), lv, lv.copy(), dv, mk, tg, bulb, force, peak,
                          X[L][L].reshape(-1, 3).copy(), L * L, its)

    def _group_keyframe(self, e1: Event, e2: Event, s1: float, s2: float, pred, x_left, what: str):
        """Equilibrium under the two events' loads added, at levels (s1, s2): from the bilinear
        predictor ``pred`` (one Newton at the full load, shifted Cholesky), else from the
        neighbour ``x_left`` with load steps."""
        fem, config = self.fem, self.config
        (f1, p1), (f2, p2) = self.loads(e1, s1), self.loads(e2, s2)
        f_ext = f1 if f2 is None else f2 if f1 is None else f1 + f2
        pres = dict(p1)
        for c, v in p2.items():
            pres[c] = pres.get(c, 0.0) + v
        pres = pres or None
        try:
            sol = solve_static(fem, f_ext, pressures=pres, x0=pred, tol=config.tol, min_load_step=1.0,
                               max_iter=25, on_indefinite="shift")
        except ElementInversionError:
            sol = None
        if sol is None or not sol.converged:
            sol = solve_static(fem, f_ext, pressures=pres, x0=x_left, tol=config.tol,
                               min_load_step=1.0 / 64, max_iter=25)
        if not sol.converged:
            raise SolverError(f"truth of {self.scenario.name}: {what}: {sol.status}")
        return sol


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def write_snapshot(truth: Truth, path) -> str:
    """VTU of the truth mesh deformed at the peak of its largest event (point data
    ``displacement_mm``, cell data ``region``)."""
    import meshio

    et = truth.peak_event()
    m = truth.model
    u = et.x_peak - m.nodes
    cells = ("tetra10", np.asarray(m.tets10)) if m.element_order == 2 else ("tetra", np.asarray(m.tets))
    mesh = meshio.Mesh(et.x_peak, [cells],
                       point_data={"displacement_mm": u * 1e3},
                       cell_data={"region": [np.asarray(m.tet_region, np.int32)]})
    meshio.write(str(path), mesh)
    return str(path)
