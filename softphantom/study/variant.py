"""Evaluate one design variant: mesh, linearize at rest and at a probe load along each axis
direction, and read off observability (W), resolution, range, mesh quality and cost.

What each figure is (docs/sweep.md has the derivations):

* ``count_<arm>_mm3``: the cavity volume change of one effective ADC count (oversampled level),
  from the sensing budget with that tube: ``V_T · (ADC span / 2^eff_bits) / P0``.
* ``W_sv1..3_mm3_per_N``, ``cond_W``: singular values and condition of the force part of W (4 × 3,
  m³/N) at rest (the estimator's ``cond_W``); ``cond_W_loaded_max`` the largest over the probe loads.
* ``obs_sv_min_mm3``: the smallest singular value of the force part of W at rest with each force
  column scaled by its range over the atlas's default load envelope: the arm volume change (mm³)
  of the least-seen force step one envelope long
  (:mod:`~softphantom.estimation.observability`); ``obs_sv_min_loaded_mm3`` the smallest over
  the probe loads.
* ``res_force_<axis>_N``: 1-σ error of the least-squares force when every arm reads with an error
  of one count (independent): N per count, through ``W_f⁺`` at rest
  (:func:`~softphantom.estimation.noise_bound`); ``res_force_worst_N`` the largest of the three.
* ``res_<x|y|z>_mm``, ``res_<yaw|pitch|roll>_deg``, ``res_target_<name>_mm`` (norm of the 3-D
  error): the same noise carried to the pose and the targets.
* ``range_<dir>_N``: the force along ``dir`` (on the contact point) at which the first arm's
  transducer leaves its rated range (Boyle with that tube). Within the probe load it comes from
  the converged non-linear volumes at rest and at the probe load (linear interpolation); beyond,
  from the linearization at the probe load (extrapolated, ``range_extrapolated``). Capped at
  ``max_force_N``. ``range_min_N`` is the smallest over the directions.
* ``mesh_*``: node and tet counts, smallest dihedral angle, worst cavity volume error (%),
  ``silicone_mL`` the meshed silicone volume; ``mesh_s``, ``solve_s``, ``total_s`` wall time,
  ``cpu_s`` the worker process's CPU time (what it costs on a quiet core).
"""

from __future__ import annotations

import functools
import json
import math
import os
import socket
import time
from typing import Any

import numpy as np

from softphantom.errors import SoftphantomError
from softphantom.study.config import DIRECTIONS, Variant
from softphantom.records.names import POSE_COLUMNS as POSE

#: Columns that measure cost, not the design: left out when two runs are compared.
TIMING_COLUMNS = ("mesh_s", "solve_s", "total_s", "cpu_s", "host")


def count_volumes_m3(cavity_volumes_m3, tube_length_m: float, tube_id_m: float, osr: int) -> np.ndarray:
    """(n,) m³: the cavity volume change of one effective count for each cavity (sensing budget).

    >>> np.round(count_volumes_m3([486e-9], 12.0, 1.2e-3, 100) * 1e9, 4).tolist()
    [0.0677]
    """
    from softphantom.sensing.budget import BudgetParams, budget

    vols = tuple(float(v) for v in cavity_volumes_m3)
    rows = budget(BudgetParams(cavity_volumes_m3=vols, group_names=tuple(str(i) for i in range(len(vols))),
                               tube_length_m=float(tube_length_m), tube_id_m=float(tube_id_m), osr=int(osr)))
    return np.array([r.resolution_mm3_datasheet * 1e-9 for r in rows])


def saturation_volumes_m3(v_total_m3: np.ndarray, p0_Pa: float) -> tuple[np.ndarray, np.ndarray]:
    """(compression, expansion) cavity volume changes (m³, negative and positive) at which each
    arm's transducer reaches the end of its rated range (Boyle over cavity + tube)."""
    from softphantom.sensing.chain import MPXV7002
    from softphantom.sensing.pneumatics import boyle_dV

    lo = boyle_dV(MPXV7002.p_max_Pa, v_total_m3, p0_Pa)  # compression: positive gauge pressure
    hi = boyle_dV(MPXV7002.p_min_Pa, v_total_m3, p0_Pa)
    return np.asarray(lo, float), np.asarray(hi, float)


def _first_crossing(V0: np.ndarray, V1: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float | None:
    """Smallest t in [0, 1] where V0 + t (V1 − V0) leaves [lo, hi] for any arm (None: never)."""
    best = None
    d = V1 - V0
    for i in range(len(V0)):
        for lim in (lo[i], hi[i]):
            if d[i] != 0.0:
                t = (lim - V0[i]) / d[i]
                if 0.0 <= t <= 1.0 and (best is None or t < best):
                    best = t
    return best


def direction_range(F: float, V_probe: np.ndarray, W_dir: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    cap: float) -> tuple[float, bool]:
    """Force (N) along one direction at which an arm leaves [lo, hi]: interpolated on [0, F]
    between rest (V = 0) and the converged volumes ``V_probe`` at F, else extrapolated from the
    tangent ``W_dir`` (m³/N) at F. Returns (force, extrapolated), capped at ``cap``.

    >>> direction_range(2.0, np.array([-1.0, 1.0]), np.array([-0.5, 0.5]), np.array([-4.0, -4.0]), np.array([4.0, 4.0]), 50.0)
    (8.0, True)
    >>> direction_range(2.0, np.array([-8.0, 1.0]), np.array([-4.0, 0.5]), np.array([-4.0, -4.0]), np.array([4.0, 4.0]), 50.0)
    (1.0, False)
    """
    t = _first_crossing(np.zeros_like(V_probe), V_probe, lo, hi)
    if t is not None:
        return min(float(t * F), float(cap)), False
    beyond = math.inf
    for i in range(len(V_probe)):
        if W_dir[i] < 0:
            beyond = min(beyond, float((lo[i] - V_probe[i]) / W_dir[i]))
        elif W_dir[i] > 0:
            beyond = min(beyond, float((hi[i] - V_probe[i]) / W_dir[i]))
    return min(float(F + beyond), float(cap)), True


def evaluate_variant(variant: Variant) -> dict[str, Any]:
    """The result row of one variant (plain floats/strings; units in the names).

    A design that cannot be built, meshed or solved gives ``status`` ``"invalid"`` or
    ``"failed"`` with its one-line ``error``; anything else propagates (the caller records it).
    """
    t0, c0 = time.perf_counter(), time.process_time()
    row: dict[str, Any] = {"variant": variant.index, "key": variant.key, "status": "ok", "error": "",
                           "host": f"{socket.gethostname()}:{os.getpid()}"}
    row.update({f"p.{k}": v for k, v in variant.params.items()})
    try:
        row.update(_evaluate(variant))
    except SoftphantomError as exc:
        row["status"], row["error"] = _why(exc)
    row["total_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.process_time() - c0  # this process's CPU: the cost on a quiet core
    return row


def _why(exc: SoftphantomError) -> tuple[str, str]:
    """(status, one-line reason) of a variant that raised ``exc``: ``invalid`` for bad input (the
    design or its mesh refused), ``failed`` for a solver."""
    from softphantom.errors import UserError

    return "invalid" if isinstance(exc, UserError) else "failed", f"{type(exc).__name__}: {exc}".splitlines()[0]


def design_problem(variant: Variant) -> str:
    """Why the design of ``variant`` is invalid, as its row's ``error`` would say ('' if it
    validates). Checks the design only (no mesh: a mesh that misses a cavity volume is found
    when the variant is evaluated)."""
    from softphantom.design import design_from_dict
    from softphantom.errors import UserError

    try:
        design_from_dict(variant.design)
    except UserError as exc:
        return _why(exc)[1]
    return ""


#: design keys that do not change the mesh (a variant differing only there reuses it)
_NOT_GEOMETRY = ("materials", "region_materials")


@functools.lru_cache(maxsize=16)
def _design(design_json: str):
    """The validated design of a design dict (JSON), kept per worker process: validating the
    geometry takes ~0.3 s, as long as the rest of a variant whose mechanics are reused."""
    from softphantom.design import design_from_dict

    return design_from_dict(json.loads(design_json))


@functools.lru_cache(maxsize=4)
def _mesh(geometry_json: str, mesh_size_mm: float | None):
    from softphantom.design import build_model

    return build_model(_design(geometry_json), mesh_size_mm)


def _model(design_json: str, mesh_size_mm: float | None):
    """The mesh of a design, kept per worker process: variants that differ only in tube or
    material reuse it (the model then carries this variant's materials)."""
    import dataclasses

    design = _design(design_json)
    geometry = {k: v for k, v in json.loads(design_json).items() if k not in _NOT_GEOMETRY}
    model = _mesh(json.dumps(geometry, sort_keys=True), mesh_size_mm)
    mats = {k: getattr(design, k) for k in _NOT_GEOMETRY if hasattr(design, k)}
    return dataclasses.replace(model, design=dataclasses.replace(model.design, **mats)) if mats else model


@functools.lru_cache(maxsize=4)
def _mechanics(design_json: str, mesh_size_mm: float | None, contact: str, contact_radius_mm: float,
               probe_force_N: float, directions: tuple[str, ...]) -> dict[str, Any]:
    """The variant's mesh figures and its linearizations (at rest and at the probe load along each
    direction), kept per worker process: variants that differ only in the pneumatic line (tube,
    OSR) or the force cap have the same mechanics and reuse them."""
    from softphantom.design.model import MM
    from softphantom.estimation import EquilibriumSolver
    from softphantom.fem import fem_from_phantom, force_actuator, probe_matrix

    design = _design(design_json)
    t = time.perf_counter()
    model = _model(design_json, mesh_size_mm)
    out: dict[str, Any] = {"mesh_s": time.perf_counter() - t}  # ~0 where this worker had meshed the same geometry
    t = time.perf_counter()
    out["mesh_nodes"] = len(model.nodes)
    out["mesh_tets"] = len(model.tets)
    out["mesh_min_dihedral_deg"] = model.min_dihedral_deg()
    errs = [abs(model.cavity_volume(k) / (v * MM**3) - 1.0) for k, v in design.cavity_volumes_mm3().items()]
    out["mesh_cavity_error_max_pct"] = 100.0 * max(errs)
    out["silicone_mL"] = float(model.tet_volumes().sum()) * 1e6

    fem = fem_from_phantom(model)  # each region's law from the design file ([materials])
    if contact not in model.p_ext:
        from softphantom.errors import UserError

        raise UserError(f"evaluate.contact {contact!r}: the model has {', '.join(sorted(model.p_ext))}")
    H_f = force_actuator(fem, model.p_ext[contact], contact_radius_mm * MM)
    pts = [*model.markers.values(), *model.targets.values()]
    cavities = model.layout.actuated  # each a known pressure, 0 at the probe load (measured: W's rows)
    eq = EquilibriumSolver(fem, H_f, probe_matrix(fem, pts), layout=model.layout)
    rest = eq.rest()
    lins = {d: eq.solve(rest, np.r_[probe_force_N * np.array(DIRECTIONS[d], float), np.zeros(len(cavities))])
            for d in directions}
    out["solve_s"] = time.perf_counter() - t
    # one token: the variant that takes it paid for these mechanics, any later one reused them
    # (list.pop is atomic: right also for workers running several variants in threads)
    return {"figures": out, "rest": rest, "lins": lins, "n_markers": len(model.markers),
            "targets": tuple(model.targets), "unclaimed": [True]}


def _evaluate(variant: Variant) -> dict[str, Any]:
    from softphantom.design.model import MM
    from softphantom.estimation import noise_bound
    from softphantom.estimation.observability import envelope_ranges, observed_state
    from softphantom.sensing.measurement import P0_STANDARD_PA
    from softphantom.sensing.pneumatics import tube_volume_m3

    s, ex = variant.settings, variant.extra
    design_json = json.dumps(variant.design, sort_keys=True)
    design = _design(design_json)
    mech = _mechanics(design_json,
                      float(ex["mesh_size_mm"]) if ex.get("mesh_size_mm") else None,
                      s.contact, float(s.contact_radius_mm), float(s.probe_force_N), tuple(s.directions))
    out: dict[str, Any] = dict(mech["figures"])
    try:
        mech["unclaimed"].pop()
    except IndexError:  # reused: no time spent on this variant's mechanics
        out["mesh_s"] = out["solve_s"] = 0.0
    solve_s = out.pop("solve_s")
    rest = mech["rest"]

    # the pneumatics see the cast cavity (design volume), not the mesh's inscribed polyhedron
    v_cav = np.array(design.sensing_volumes_mm3()) * MM**3  # the volume channels: W's rows
    v_tube = tube_volume_m3(float(ex["sensing.tube_length_m"]), float(ex["sensing.tube_id_mm"]) * MM)
    q = count_volumes_m3(v_cav, float(ex["sensing.tube_length_m"]), float(ex["sensing.tube_id_mm"]) * MM,
                         int(ex["sensing.osr"]))
    for a, qa in zip(design.sensing_names, q):
        out[f"count_{a}_mm3"] = qa * 1e9
    sv = np.linalg.svd(rest.W[:, :3], compute_uv=False)
    for i, v in enumerate(sv):
        out[f"W_sv{i + 1}_mm3_per_N"] = v * 1e9
    out["cond_W"] = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    env_ranges = envelope_ranges(m=len(design.pressure_names))
    out["obs_sv_min_mm3"] = float(observed_state(rest, env_ranges).sv_force_mm3[-1])

    nb = noise_bound(rest, rest.sub_x[: mech["n_markers"]], mech["targets"], q)  # as the Estimator
    for ax, v in zip("xyz", nb.force_N):
        out[f"res_force_{ax}_N"] = float(v)
    out["res_force_worst_N"] = float(nb.force_N.max())
    pose = np.r_[nb.pose[:3] * 1e3, np.degrees(nb.pose[3:])]
    for name, v in zip(POSE, pose):
        out[f"res_{name}"] = float(v)
    tnorm = {k: float(np.linalg.norm(v)) * 1e3 for k, v in nb.target_m.items()}
    for k, v in tnorm.items():
        out[f"res_target_{k}_mm"] = v
    out["res_target_worst_mm"] = max(tnorm.values()) if tnorm else math.nan

    lo, hi = saturation_volumes_m3(v_cav + v_tube, P0_STANDARD_PA)
    conds, ranges, extrap = [], {}, False
    for d in s.directions:
        u = np.array(DIRECTIONS[d], float)
        lin = mech["lins"][d]
        svl = np.linalg.svd(lin.W[:, :3], compute_uv=False)
        conds.append(float(svl[0] / svl[-1]) if svl[-1] > 0 else math.inf)
        r, e = direction_range(s.probe_force_N, lin.V, lin.W[:, :3] @ u, lo, hi, s.max_force_N)
        ranges[d] = r
        extrap |= e
        out[f"range_{d}_N"] = r
        out[f"cond_W_{d}"] = conds[-1]
    out["cond_W_loaded_max"] = max(conds) if conds else math.nan
    out["obs_sv_min_loaded_mm3"] = min((float(observed_state(mech["lins"][d], env_ranges).sv_force_mm3[-1])
                                        for d in s.directions), default=math.nan)
    out["range_min_N"] = min(ranges.values()) if ranges else math.nan
    out["range_min_dir"] = min(ranges, key=ranges.get) if ranges else ""
    out["range_extrapolated"] = bool(extrap)
    out["solve_s"] = solve_s
    return out
