"""Which law and element should the estimator use? Accuracy against the converged reference vs the
cost of one equilibrium solve, per law × element order × mesh size
(docs/model.md).

    .venv/bin/python benchmarks/bench_model_choice.py [--laws corotational neo-hookean]
        [--p1 9 6 4.5] [--p2 12 9] [--p2-arm-mm 2 1.5] [--json out.json] [--estimator-cost]

Load: the on-centre push of DESIGN.md §5, (0.15, 2.5, −0.2) N on a 4 mm patch (the reference's
uniform-traction patch for every model, so only the model differs). Each model is softphantom's
own (``build_fem`` with the law, ``solve_static`` from rest to 1e-8); the read-outs (marker pose,
arm ΔV) use the reference helpers of tests/reference/felupe_bip.py for every model alike. The
converged reference: neo-Hookean P2 on the default (filleted) design, 9 mm bulk, 1.0 mm arms
(docs/model.md: within 0.2 % of the next finer settings). Cost: the model's build, one tangent
assembly + Cholesky factorization (what an estimator refresh pays per re-factorization), and
the full Newton solve from rest, wall seconds; a peer ratio against P1 co-rotational at the
estimator's 6 mm in the same run.

``--estimator-cost`` measures instead what the estimator pays on each model, through its own
:class:`~softphantom.estimation.forward.ForwardModel` on the design meshed at that size and order
(4 mm patch, on-centre): the rest linearization (assembly, factorization, sensitivities; what
building an estimator costs), a converged solve from rest at the push, a refresh 0.25 N further
along y (``relinearize_N``: a refresh of the sync estimator) and a 1 N neighbour step (what each of
the atlas's grid solves costs: they start from a converged neighbour about 1 N away), and the atlas
build time this implies for the default grid (5·7·5·4 = 700 solves) on 1 and 2 workers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "reference"))

from _results import add_results_option, grouped, write_table  # noqa: E402
from felupe_bip import bip_tet10, cavity_volumes, corner_mesh, patch_load, probe  # noqa: E402

from softphantom.design import BIPDesign  # noqa: E402
from softphantom.fem import SparseSolver, build_fem, free_tangent, solve_static  # noqa: E402
from softphantom.fem import material as M  # noqa: E402
from softphantom.pose import pose_of_markers  # noqa: E402

ARMS = ("front_zpos", "front_zneg", "back_xpos", "back_xneg")
# The default design (2 mm junction fillets), NH P2, 9 mm with the arms at 1.0 mm: converged within
# 0.2 % in y and yaw along both the bulk and the arm size (docs/model.md, "With a junction fillet";
# softphantom's NH on the reference mesh, equal to FElupe's to 1e-9). The sharp design's reference
# (FElupe NH P2 4.5 mm: y 5.644 mm, yaw 5.207°) was not converged in yaw (a singular edge).
REFERENCE = {"y_mm": 5.529, "yaw_deg": 4.669, "dV_mm3": [10.91, 8.80, -12.02, -8.06]}
FORCE = np.array([0.15, 2.5, -0.2])


def make_law(name: str, E: float, nu: float):
    return {"corotational": M.Corotational, "neo-hookean": M.NeoHookean}[name](E, nu, 1070.0)


def run(mesh, law) -> dict:
    n = len(mesh.nodes)
    t0 = time.perf_counter()
    fem = build_fem(mesh.nodes, mesh.tets, law, mesh.fixed_nodes)
    t_build = time.perf_counter() - t0
    f = patch_load(mesh.nodes, mesh.outer, n, mesh.points["on-centre"], FORCE, 4e-3)
    t0 = time.perf_counter()
    K = free_tangent(fem, fem.x_rest)
    SparseSolver("auto").factorize(K)
    t_factor = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = solve_static(fem, f)
    t_solve = time.perf_counter() - t0
    markers = [k for k in mesh.points if k.startswith("m") and k[1:].isdigit()]
    P = probe(mesh, np.array([mesh.points[k] for k in markers]))
    pose = pose_of_markers(P @ mesh.nodes, (P @ sol.x)[None]).to_mm_deg()[0]
    V0, V1 = cavity_volumes(mesh, mesh.nodes), cavity_volumes(mesh, sol.x)
    dv = np.array([(V1[k] - V0[k]) * 1e9 for k in ARMS])
    ref_dv = np.array(REFERENCE["dV_mm3"])
    return {
        "nodes": n, "converged": bool(sol.converged), "newton_iterations": sol.iterations,
        "y_mm": round(float(pose[1]), 3), "yaw_deg": round(float(pose[3]), 3),
        "dV_mm3": [round(float(v), 2) for v in dv],
        "err_y_mm": round(float(pose[1]) - REFERENCE["y_mm"], 3),
        "err_yaw_deg": round(float(pose[3]) - REFERENCE["yaw_deg"], 3),
        "err_dV_rms_mm3": round(float(np.sqrt(np.mean((dv - ref_dv) ** 2))), 2),
        "build_s": round(t_build, 2), "factor_s": round(t_factor, 3), "solve_s": round(t_solve, 2),
    }


def estimator_cost(a) -> int:
    import dataclasses
    import os

    from softphantom.design import build_model
    from softphantom.errors import SolverError
    from softphantom.estimation import EstimatorConfig
    from softphantom.estimation.forward import ForwardModel
    from softphantom.fem import fem_from_phantom

    print(f"load average {os.getloadavg()[0]:.1f}", flush=True)
    rows = []
    lam = np.r_[FORCE, 0.0]
    for order, sizes in ((1, a.p1), (2, a.p2)):
        base = BIPDesign()
        design = dataclasses.replace(base, mesh=dataclasses.replace(base.mesh, element_order=order))
        for h in sizes:
            model = build_model(design, h)
            for lname in a.laws:
                fem = fem_from_phantom(model, make_law(lname, a.E_kPa * 1e3, a.nu), order=order)
                t0 = time.perf_counter()
                fwd = ForwardModel(model, EstimatorConfig(), fem=fem)
                t_rest = time.perf_counter() - t0
                t0 = time.perf_counter()
                lin = fwd.solve(lam)
                t_push = time.perf_counter() - t0
                t0 = time.perf_counter()
                fwd.eq.solve(lin, lam + [0.0, 0.25, 0.0, 0.0])
                t_refresh = time.perf_counter() - t0
                t0 = time.perf_counter()
                try:
                    fwd.solve(lam + [0.0, 1.0, 0.0, 0.0], lin)
                    t_step = time.perf_counter() - t0
                except SolverError as exc:  # a finding, not a crash: this model cannot reach that load
                    print(f"{lname} P{order} {h:g} mm: 1 N step failed: {exc}", flush=True)
                    t_step = float("nan")
                r = {"law": lname, "order": order, "mesh_size_mm": h, "nodes": fem.n_nodes,
                     "rest_s": round(t_rest, 2), "push_s": round(t_push, 2), "refresh_s": round(t_refresh, 2),
                     "step_1N_s": round(t_step, 2), "atlas_700_1w_min": round(700 * t_step / 60, 1),
                     "atlas_700_2w_min": round(700 * t_step / 120, 1), "load": round(os.getloadavg()[0], 1)}
                rows.append(r)
                print(f"{lname:13s} P{order} {h:4g} mm {r['nodes']:6d} nodes: rest linearization {r['rest_s']} s, "
                      f"push from rest {r['push_s']} s, refresh +0.25 N {r['refresh_s']} s, 1 N step {r['step_1N_s']} s "
                      f"-> atlas 700 solves ≈ {r['atlas_700_1w_min']} min (1 worker), {r['atlas_700_2w_min']} min (2); "
                      f"load {r['load']}", flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--laws", nargs="+", default=["corotational", "neo-hookean"])
    ap.add_argument("--p1", type=float, nargs="*", default=[9.0, 6.0, 4.5])
    ap.add_argument("--p2", type=float, nargs="*", default=[12.0, 9.0])
    ap.add_argument("--p2-arm-mm", type=float, nargs="*", default=[],
                    help="P2 only: also mesh each --p2 size with the arms at these element sizes (mm; the "
                         "default grading scales the arms with the bulk: 3 mm at 6 mm)")
    ap.add_argument("--E-kPa", type=float, default=142.3)
    ap.add_argument("--nu", type=float, default=0.45)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--estimator-cost", action="store_true", help="the estimator's costs per model (see above)")
    add_results_option(ap, "model_choice")
    a = ap.parse_args(argv)
    if a.estimator_cost:
        return estimator_cost(a)
    rows = []
    meshes = {}
    import dataclasses

    settings = [(1, h, None) for h in a.p1] + [(2, h, None) for h in a.p2]
    settings += [(2, h, arm) for h in a.p2 for arm in a.p2_arm_mm]
    for order, h, arm in settings:
        if (order, h, arm) not in meshes:
            design = BIPDesign()
            design = dataclasses.replace(design, mesh=design.mesh.scaled_to(h))
            if arm is not None:
                design = dataclasses.replace(design, mesh=dataclasses.replace(design.mesh, arm_size_mm=arm))
            meshes[(order, h, arm)] = bip_tet10(design, None, order=order)
        for lname in a.laws:
            r = run(meshes[(order, h, arm)], make_law(lname, a.E_kPa * 1e3, a.nu))
            r.update(law=lname, order=order, mesh_size_mm=h, arm_size_mm=arm)
            rows.append(r)
            where = f"{h:4g} mm" + (f", arms {arm:g} mm" if arm is not None else "")
            print(f"{lname:13s} P{order} {where} {r['nodes']:6d} nodes: y {r['y_mm']:.3f} ({r['err_y_mm']:+.3f} mm, "
                  f"{r['err_y_mm'] / REFERENCE['y_mm']:+.1%}), yaw {r['yaw_deg']:.3f} ({r['err_yaw_deg']:+.3f}°, "
                  f"{r['err_yaw_deg'] / REFERENCE['yaw_deg']:+.1%}), arm dV {r['dV_mm3']} (RMS err "
                  f"{r['err_dV_rms_mm3']} mm³); build {r['build_s']} s, factor {r['factor_s']} s, "
                  f"solve {r['solve_s']} s ({r['newton_iterations']} it)", flush=True)
    peer = next((r for r in rows if r["law"] == "corotational" and r["order"] == 1 and r["mesh_size_mm"] == 6.0), None)
    if peer:
        print("\ncost relative to P1 co-rotational 6 mm (the estimator's model today), same run:")
        for r in rows:
            print(f"  {r['law']:13s} P{r['order']} {r['mesh_size_mm']:4g} mm: factor x{r['factor_s'] / peer['factor_s']:.1f}, "
                  f"solve x{r['solve_s'] / peer['solve_s']:.1f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    write_table(a.results_name, ("law", "element", "mesh mm", "nodes", "y error mm", "yaw error °",
                                 "arm ΔV RMS error mm³", "factorization s", "solve s"), [(
        r["law"], f"P{r['order']}", f"{r['mesh_size_mm']:g}" + (f", arms {r['arm_size_mm']:g}" if r["arm_size_mm"] else ""),
        grouped(r["nodes"]), f"{r['err_y_mm']:+.2f}", f"{r['err_yaw_deg']:+.2f}", f"{r['err_dV_rms_mm3']:.2f}",
        f"{r['factor_s']:.2f}", f"{r['solve_s']:.1f}") for r in rows],
        caption=f"Errors against the converged reference (y {REFERENCE['y_mm']} mm, yaw {REFERENCE['yaw_deg']}°):")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
