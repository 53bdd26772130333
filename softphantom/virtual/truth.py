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
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

import dataclasses

from softphantom.design import PhantomModel, build_model, design_to_dict
from softphantom.errors import DesignError, MeshError, SolverError, UserError
from softphantom.fem import (
    Corotational,
    ElementInversionError,
    NeoHookean,
    cavity_volume,
    fem_from_phantom,
    force_actuator,
    probe_matrix,
    solve_static,
)
from softphantom.fem.model import laws_of_design
from softphantom.pose import Pose6, pose_of_markers
from softphantom.progress import report
from softphantom.virtual.scenario import Event, Scenario

TRUTH_LAWS = ("neo-hookean", "model")

log = logging.getLogger(__name__)


def truth_laws(model: PhantomModel, law: str) -> dict:
    """Region name -> the truth's law object: the design's laws, co-rotational ones replaced by
    their neo-Hookean twin (same E, ν, density) unless ``law == "model"``."""
    by_region = laws_of_design(model.design, model.regions)
    if law == "model":
        return by_region
    return {k: NeoHookean(v.E_Pa, v.nu, v.density_kg_m3) if isinstance(v, Corotational) else v
            for k, v in by_region.items()}


@dataclass(frozen=True)
class TruthConfig:
    """``mesh_scale`` truth node spacing / the model's (:func:`truth_model`); ``levels`` keyframes per push ramp (interpolated
    between: at 3, the P2 Yeoh calibration truth's yaw is off by up to 0.16° mid-ramp, at 9 by
    0.01°; docs/calibration.md);
    ``tol`` Newton's relative residual; ``inflate_steps`` pressure steps up to the limit;
    ``law``: ``"neo-hookean"`` (co-rotational regions become compressible neo-Hookean with the
    same E, ν, density) or ``"model"`` (the design's own laws, as the estimator); ``order``: the
    truth's element order, 2 (10-node tets, the default) or 1 (4-node, e.g. for fast tests).

    >>> TruthConfig(order=3)
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: truth order must be 1 or 2, got 3
    """

    mesh_scale: float = 0.75
    levels: int = 3
    tol: float = 1e-8
    inflate_steps: int = 10
    law: str = "neo-hookean"
    order: int = 2

    def __post_init__(self) -> None:
        if self.law not in TRUTH_LAWS:
            raise UserError(f"truth law must be one of {', '.join(TRUTH_LAWS)}, got {self.law!r}")
        if isinstance(self.order, bool) or self.order not in (1, 2):
            raise UserError(f"truth order must be 1 or 2, got {self.order!r}")


@dataclass(frozen=True, eq=False)
class EventTruth:
    """Keyframes of one event: ``s`` (K,) levels from 0 to 1; ``dV`` (K, cavities) m³ cavity volume
    changes (the arms, then the internal cavities); ``markers`` (K, k, 3) m positions; ``targets``
    (K, t, 3) m displacements; ``bulb_dV`` (K,) m³ change of the volume the outer surface encloses;
    peak load ``force`` (3,) N and ``p_Pa``, the gauge pressure of the inflated cavity
    (``cavity``; 0 for a push); ``x_peak`` (N, 3) truth-mesh nodes at s = 1; ``iterations``
    Newton iterations; ``note`` what happened (e.g. a limit reached)."""

    event: Event
    s: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    bulb_dV: np.ndarray
    force: np.ndarray
    p_Pa: float
    x_peak: np.ndarray
    iterations: int
    note: str = ""

    @property
    def cavity(self) -> str | None:
        """The internal cavity the event inflates (None for a push)."""
        return self.event.cavity if self.event.kind == "inflate" else None

    @property
    def p_urethra(self) -> float:
        """The urethra's peak gauge pressure (Pa) in this event."""
        return self.p_Pa if self.cavity == "urethra" else 0.0

    def _interp(self, arr: np.ndarray, s: np.ndarray) -> np.ndarray:
        f = PchipInterpolator(self.s, arr.reshape(len(self.s), -1), axis=0)
        return f(np.clip(s, 0.0, 1.0)).reshape((len(s),) + arr.shape[1:])


def pchip_rows(x: np.ndarray, Y: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Row n of ``Y`` (n, K, D) interpolated at ``q[n]`` by the monotone cubic through (``x``,
    Y[n]) (scipy's :class:`~scipy.interpolate.PchipInterpolator`, one per row, vectorized; linear
    for K = 2); ``q`` clipped to [x0, x_K-1]. (n, D).

    >>> x = np.array([0.0, 0.5, 1.0]); Y = np.array([[[0.0], [1.0], [4.0]], [[2.0], [2.0], [0.0]]])
    >>> pchip_rows(x, Y, np.array([0.25, 1.0])).ravel().tolist() == [
    ...     float(PchipInterpolator(x, Y[0, :, 0])(0.25)), 0.0]
    True
    """
    x = np.asarray(x, float)
    Y = np.asarray(Y, float)
    q = np.clip(np.asarray(q, float), x[0], x[-1])
    h = np.diff(x)
    m = np.diff(Y, axis=1) / h[None, :, None]  # (n, K-1, D) secant slopes
    d = np.empty_like(Y)
    if len(x) == 2:
        d[:] = m
    else:
        # interior: weighted harmonic mean of equal-signed neighbouring slopes, else 0 (Fritsch–Butland)
        w1 = (2 * h[1:] + h[:-1])[None, :, None]
        w2 = (h[1:] + 2 * h[:-1])[None, :, None]
        same = (np.sign(m[:, :-1]) == np.sign(m[:, 1:])) & (m[:, :-1] != 0) & (m[:, 1:] != 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            whm = (w1 / m[:, :-1] + w2 / m[:, 1:]) / (w1 + w2)
            d[:, 1:-1] = np.where(same, 1.0 / whm, 0.0)

        def edge(h0, h1, m0, m1):
            e = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
            e = np.where(np.sign(e) != np.sign(m0), 0.0, e)
            return np.where((np.sign(m0) != np.sign(m1)) & (np.abs(e) > 3 * np.abs(m0)), 3 * m0, e)

        d[:, 0] = edge(h[0], h[1], m[:, 0], m[:, 1])
        d[:, -1] = edge(h[-1], h[-2], m[:, -1], m[:, -2])
    k = np.clip(np.searchsorted(x, q, side="right") - 1, 0, len(x) - 2)
    r = np.arange(len(q))
    hk = h[k][:, None]
    t = ((q - x[k]) / h[k])[:, None]
    return ((2 * t**3 - 3 * t**2 + 1) * Y[r, k] + (t**3 - 2 * t**2 + t) * hk * d[r, k]
            + (-2 * t**3 + 3 * t**2) * Y[r, k + 1] + (t**3 - t**2) * hk * d[r, k + 1])


@dataclass(frozen=True, eq=False)
class GroupTruth:
    """Keyframes of two events acting at once (``pair``: their indices in the scenario's events):
    on the tensor grid of their levels ``s1`` × ``s2`` ((L+1,) each, from 0 to 1), ``dV`` (L+1,
    L+1, cavities) m³, ``markers`` (L+1, L+1, k, 3) m, ``targets`` (L+1, L+1, t, 3) m, ``bulb_dV``
    (L+1, L+1) m³; row 0 and column 0 are the other event alone. At (1, 1): ``force`` (3,) N the
    sum of the peak forces, ``pressures_Pa`` {cavity: Pa}, ``x_peak`` (N, 3) truth-mesh nodes;
    ``solves``, ``iterations`` Newton's for the L² inner keyframes."""

    pair: tuple[int, int]
    events: tuple[Event, Event]
    s1: np.ndarray
    s2: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    bulb_dV: np.ndarray
    force: np.ndarray
    pressures_Pa: dict
    x_peak: np.ndarray
    solves: int
    iterations: int

    def interp(self, arr: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``arr`` (a grid of this group) at levels (a, b) (n,): PCHIP along s1, then along s2."""
        n1, n2 = len(self.s1), len(self.s2)
        rows = PchipInterpolator(self.s1, arr.reshape(n1, -1), axis=0)(np.clip(a, 0.0, 1.0))
        out = pchip_rows(self.s2, rows.reshape(len(a), n2, -1), b)
        return out.reshape((len(a),) + arr.shape[2:])


@dataclass(frozen=True, eq=False)
class TruthSamples:
    """The truth at times ``t`` (n,) s (scenario clock): ``force`` (n, 3) N, ``pressures`` (n, M)
    Pa gauge of the actuated internal cavities ``cavity_names``, ``dV`` (n, cavities) m³ (the arms,
    then every internal cavity, actuated or measured), ``markers`` (n, k, 3) m, ``targets`` (n, t, 3) m displacement,
    ``pose`` of the marker rigid body relative to rest."""

    t: np.ndarray
    force: np.ndarray
    pressures: np.ndarray
    dV: np.ndarray
    markers: np.ndarray
    targets: np.ndarray
    pose: Pose6
    cavity_names: tuple[str, ...] = ("urethra",)

    @property
    def p_urethra(self) -> np.ndarray:
        """(n,) Pa, the urethra's gauge pressure (NaN without a urethra)."""
        if "urethra" not in self.cavity_names:
            return np.full(len(self.t), np.nan)
        return self.pressures[:, self.cavity_names.index("urethra")]


@dataclass(frozen=True, eq=False)
class Truth:
    """The solved truth of a scenario on ``model`` (the truth mesh): ``rest_markers`` (k, 3) m,
    ``marker_names``, ``target_names``, ``rest_volumes`` (cavities,) m³, ``events`` keyframes,
    ``solve_s`` wall time, ``config``."""

    scenario: Scenario
    model: PhantomModel
    marker_names: tuple[str, ...]
    target_names: tuple[str, ...]
    rest_markers: np.ndarray
    rest_volumes: np.ndarray
    events: tuple[EventTruth, ...]
    solve_s: float
    config: TruthConfig = field(default_factory=TruthConfig)
    groups: tuple[GroupTruth, ...] = ()
    cached: bool = False  # read from the truth cache (solve_s: the solve that wrote it)

    def sample(self, t) -> TruthSamples:
        """The truth at times ``t`` (s), interpolated in load level (see the module docstring)."""
        t = np.atleast_1d(np.asarray(t, float))
        n, k, nt = len(t), len(self.marker_names), len(self.target_names)
        cav = tuple(self.model.design.pressure_names)  # the loads; a measured cavity is read, in dV
        force = np.zeros((n, 3))
        p = np.zeros((n, len(cav)))
        dV = np.zeros((n, len(self.model.design.cavity_names)))  # the arms, then the internal cavities
        markers = np.broadcast_to(self.rest_markers, (n, k, 3)).copy()
        targets = np.zeros((n, nt, 3))
        for et in self.events:
            e = et.event
            sel = e.acting(t)
            if not sel.any():
                continue
            s = e.level(t[sel])
            force[sel] = s[:, None] * et.force
            if et.cavity is not None:
                p[sel, cav.index(et.cavity)] = s * et.p_Pa
            dV[sel] = et._interp(et.dV, s)
            markers[sel] = et._interp(et.markers, s)
            targets[sel] = et._interp(et.targets, s)
        for g in self.groups:  # both events acting: the group's two-parameter path
            e1, e2 = g.events
            sel = e1.acting(t) & e2.acting(t)
            if not sel.any():
                continue
            a, b = e1.level(t[sel]), e2.level(t[sel])
            force[sel] = 0.0
            p[sel] = 0.0
            for e, lv in ((e1, a), (e2, b)):
                if e.kind == "push":
                    force[sel] += lv[:, None] * np.asarray(e.force_N, float)
                else:
                    p[sel, cav.index(e.cavity)] += lv * e.p_kPa * 1e3
            dV[sel] = g.interp(g.dV, a, b)
            markers[sel] = g.interp(g.markers, a, b)
            targets[sel] = g.interp(g.targets, a, b)
        pose = pose_of_markers(self.rest_markers, markers)
        return TruthSamples(t, force, p, dV, markers, targets, pose, cav)

    def peak_event(self) -> EventTruth | GroupTruth:
        """The event (or group, at both peaks) whose peak moves the markers most (for the snapshot
        at peak load)."""
        def shift(x):
            peak = x.markers[-1, -1] if isinstance(x, GroupTruth) else x.markers[-1]
            return float(np.abs(peak - self.rest_markers).max())

        return max((*self.events, *self.groups), key=shift)

    def summary(self) -> dict:
        """Peak figures per event (mm, N, kPa, % bulb growth), JSON-able."""
        out = []
        cav = tuple(self.model.design.pressure_names)
        for et in self.events:
            # the BIP's figures as they were; another design's name the inflated cavity and its pressure
            p = (dict(p_urethra_kPa=round(et.p_urethra / 1e3, 3)) if cav == ("urethra",) else
                 dict(cavity=et.cavity, p_kPa=round(et.p_Pa / 1e3, 3)) if et.cavity else {})
            d = dict(kind=et.event.kind, start_s=et.event.start_s,
                     force_N=[round(float(f), 4) for f in et.force], **p,
                     peak_marker_shift_mm=round(float(np.linalg.norm(et.markers[-1] - self.rest_markers, axis=1).max()) * 1e3, 3),
                     peak_dV_mm3={c: round(float(v) * 1e9, 3) for c, v in zip(self.model.design.cavity_names,
                                                                                et.dV[-1])},
                     bulb_growth_percent=round(float(et.bulb_dV[-1] / self.model.bulb_volume()) * 100, 3),
                     keyframes=len(et.s) - 1, newton_iterations=et.iterations)
            for name, dsp in zip(self.target_names, et.targets[-1]):
                d[f"{name}_shift_mm"] = round(float(np.linalg.norm(dsp)) * 1e3, 3)
            if et.note:
                d["note"] = et.note
            if et.event.repeat > 1:
                d.update(repeat=et.event.repeat, period_s=et.event.period_s)
            out.append(d)
        laws = sorted({law.name for law in truth_laws(self.model, self.config.law).values()})
        extra = {"groups": [self._group_summary(g) for g in self.groups]} if self.groups else {}
        return {"truth_mesh": {"nodes": len(self.model.nodes), "tets": len(self.model.tets),
                               "mesh_size_mm": self.model.design.mesh.size_mm,
                               "element_order": self.model.element_order},
                "law": "+".join(laws), "patch_radius_mm": self.scenario.patch_radius_mm,
                "solve_s": round(self.solve_s, 2), **({"cached": True} if self.cached else {}), "events": out,
                **extra}

    def _group_summary(self, g: GroupTruth) -> dict:
        """A group's figures at both peaks (levels (1, 1)), JSON-able."""
        d = dict(events=[f"{e.kind}" + (f" {e.cavity}" if e.kind == "inflate" else "") + f" at {e.start_s:g} s"
                         for e in g.events],
                 force_N=[round(float(f), 4) for f in g.force],
                 p_kPa={c: round(v / 1e3, 3) for c, v in g.pressures_Pa.items()},
                 peak_marker_shift_mm=round(float(np.linalg.norm(g.markers[-1, -1] - self.rest_markers,
                                                                 axis=1).max()) * 1e3, 3),
                 peak_dV_mm3={c: round(float(v) * 1e9, 3) for c, v in zip(self.model.design.cavity_names,
                                                                            g.dV[-1, -1])},
                 bulb_growth_percent=round(float(g.bulb_dV[-1, -1] / self.model.bulb_volume()) * 100, 3),
                 keyframes=g.solves, newton_iterations=g.iterations)
        for name, dsp in zip(self.target_names, g.targets[-1, -1]):
            d[f"{name}_shift_mm"] = round(float(np.linalg.norm(dsp)) * 1e3, 3)
        return d


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


# --- the truth cache ----------------------------------------------------------------------------

#: Bumped when what a solve produces for the same inputs changes, so older entries are not read.
TRUTH_CACHE_FORMAT = 1
#: The environment variable naming the cache directory ("": no cache).
CACHE_ENV = "SOFTPHANTOM_CACHE_DIR"
_EVENT_ARRAYS = ("s", "dV", "markers", "targets", "bulb_dV", "force", "x_peak")
_GROUP_ARRAYS = ("s1", "s2", "dV", "markers", "targets", "bulb_dV", "force", "x_peak")


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def truth_cache_dir() -> Path | None:
    """Where solved truths are kept: ``$SOFTPHANTOM_CACHE_DIR`` (empty: nowhere), else
    ``$XDG_CACHE_HOME/softphantom``, else ``~/.cache/softphantom``; each truth under
    ``truth/<key>/`` (:func:`truth_key`)."""
    given = os.environ.get(CACHE_ENV)
    if given is not None:
        return Path(given).expanduser() if given.strip() else None
    base = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(base) if base else Path.home() / ".cache") / "softphantom"


def _scenario_dict(sc: Scenario) -> dict:
    """What a truth depends on in a scenario: its loads and their timing shape (not its name,
    description or file)."""
    d = dataclasses.asdict(sc)
    for k in ("name", "description", "source", "duration_s", "rest_s"):
        d.pop(k)
    for e in d["events"]:  # when an event starts and ends changes no keyframe: only its load path
        for k in ("start_s", "rise_s", "hold_s", "fall_s", "repeat", "period_s"):
            e.pop(k)
    d["groups"] = [list(g) for g in sc.groups]  # which events act at once: the two-parameter paths
    return d


def _model_digest(h, model: PhantomModel) -> None:
    h.update(json.dumps(design_to_dict(model.design), sort_keys=True).encode())
    for a in (model.nodes, model.tets, getattr(model, "tets10", None)):
        if a is not None:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())


def truth_key(scenario: Scenario, model: PhantomModel, config: TruthConfig,
              truth_mesh: PhantomModel | None = None) -> str:
    """SHA-256 (hex) of what a solved truth depends on: the model (its design and mesh; or the
    given truth mesh), the scenario's load paths (:func:`_scenario_dict`, its cavities named:
    ``scenario`` as :func:`solve_truth` checked it), the truth settings and
    :data:`TRUTH_CACHE_FORMAT`. Only the inputs as given: no number computed while solving."""
    h = hashlib.sha256()
    _model_digest(h, model)
    if truth_mesh is not None:
        h.update(b"truth mesh")
        _model_digest(h, truth_mesh)
    h.update(json.dumps({"format": TRUTH_CACHE_FORMAT, "config": dataclasses.asdict(config),
                         "scenario": _scenario_dict(scenario)}, sort_keys=True).encode())
    return h.hexdigest()


def save_truth(truth: Truth, entry: Path, key: str) -> None:
    """Keep ``truth`` in the cache directory ``entry`` (its truth mesh, keyframes and peak states):
    written beside it and moved into place, so a reader never sees half an entry. A cache that
    cannot be written is logged and left out (the run goes on)."""
    from softphantom.design import save_model

    entry = Path(entry)
    tmp = entry.with_name(f".{entry.name}.{os.getpid()}.tmp")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        save_model(truth.model, tmp / "truth_model", mesh_files=False)
        arrays = {"rest_markers": truth.rest_markers, "rest_volumes": truth.rest_volumes}
        for i, et in enumerate(truth.events):
            arrays.update({f"e{i}_{k}": np.asarray(getattr(et, k)) for k in _EVENT_ARRAYS})
        for i, g in enumerate(truth.groups):
            arrays.update({f"g{i}_{k}": np.asarray(getattr(g, k)) for k in _GROUP_ARRAYS})
        np.savez(tmp / "truth.npz", **arrays)
        meta = {"key": key, "format": TRUTH_CACHE_FORMAT, "solve_s": truth.solve_s,
                "marker_names": list(truth.marker_names), "target_names": list(truth.target_names),
                "events": [{"p_Pa": et.p_Pa, "iterations": et.iterations, "note": et.note} for et in truth.events],
                "groups": [{"pair": list(g.pair), "pressures_Pa": g.pressures_Pa, "solves": g.solves,
                            "iterations": g.iterations} for g in truth.groups]}
        (tmp / "truth.json").write_text(json.dumps(meta, sort_keys=True), encoding="utf-8")
        entry.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(tmp, entry)
        except OSError:  # another run kept the same truth first
            shutil.rmtree(tmp, ignore_errors=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        log.warning("truth cache: cannot write %s (%s); the truth is not kept", entry, exc.strerror or exc)


def load_truth(entry: Path, scenario: Scenario, config: TruthConfig) -> Truth | None:
    """The truth kept in ``entry`` for ``scenario`` (as :func:`solve_truth` checked it), or None when
    there is none or it cannot be read (it is then solved again)."""
    from softphantom.design import load_model

    entry = Path(entry)
    if not (entry / "truth.json").is_file():
        return None
    try:
        meta = json.loads((entry / "truth.json").read_text(encoding="utf-8"))
        if meta.get("format") != TRUTH_CACHE_FORMAT or len(meta["events"]) != len(scenario.events):
            return None
        tm = load_model(entry / "truth_model")
        with np.load(entry / "truth.npz", allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        events = tuple(EventTruth(e, *(a[f"e{i}_{k}"] for k in _EVENT_ARRAYS[:6]), float(m["p_Pa"]),
                                  a[f"e{i}_x_peak"], int(m["iterations"]), m["note"])
                       for i, (e, m) in enumerate(zip(scenario.events, meta["events"])))
        groups = tuple(GroupTruth(tuple(m["pair"]), tuple(scenario.events[j] for j in m["pair"]),
                                  *(a[f"g{i}_{k}"] for k in _GROUP_ARRAYS[:7]), dict(m["pressures_Pa"]),
                                  a[f"g{i}_x_peak"], int(m["solves"]), int(m["iterations"]))
                       for i, m in enumerate(meta["groups"]))
    except (OSError, ValueError, KeyError, TypeError, UserError) as exc:
        log.warning("truth cache: %s cannot be read (%s); solving the truth again", entry, exc)
        return None
    return Truth(scenario, tm, tuple(meta["marker_names"]), tuple(meta["target_names"]), a["rest_markers"],
                 a["rest_volumes"], events, float(meta["solve_s"]), config, groups, cached=True)


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
